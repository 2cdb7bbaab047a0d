//! The behaviour policies an actor can run beyond `uavmeta_world`'s heuristics: a Q-network's
//! greedy policy, and the online DQN agent whose replay buffer becomes the paper's datasets.

pub mod dqn_online;
pub mod q_policy;

use uavmeta_learner::checkpoint;
use uavmeta_proto::config::Config;

use q_policy::QPolicy;
use uavmeta_world::heuristics::{EpsilonPolicy, PolicyError, PolicySpec};
use uavmeta_world::rollout::Policy;

/// `spec`'s policy for `config`'s world, its random stream seeded by `seed`, asked for `steps`
/// actions in all (`PolicySpec::build`), and also `q:P:FILE`: checkpoint FILE's network, loaded
/// under `config`, greedy with a uniform random action with probability P.
pub fn build(
    spec: &PolicySpec,
    config: &Config,
    seed: u64,
    steps: Option<usize>,
) -> Result<Box<dyn Policy>, PolicyError> {
    match spec {
        PolicySpec::Checkpoint { epsilon, path } => {
            let (q, _) = checkpoint::load(path, config).map_err(|error| PolicyError::Spec {
                spec: spec.to_string(),
                expected: format!("a Q-network checkpoint: {}", chain(&error)),
            })?;
            let greedy = Box::new(QPolicy::new(q));
            spec.for_world(
                config,
                Box::new(EpsilonPolicy::around(greedy, *epsilon, seed)),
            )
        }
        spec => spec.build(config, seed, steps),
    }
}

/// `error` and its sources, joined by ": ".
fn chain(error: &dyn std::error::Error) -> String {
    let mut text = error.to_string();
    let mut source = error.source();
    while let Some(cause) = source {
        text.push_str(&format!(": {cause}"));
        source = cause.source();
    }
    text
}
