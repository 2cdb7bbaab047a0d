//! Meta-train data for the tests of this crate: a cheap behaviour policy's transitions (the
//! stalest heuristic with 10% random actions) in a task's world, so that a test takes seconds.

use uavmeta_actors::collect::Collector;
use uavmeta_learner::transitions::Transitions;
use uavmeta_meta::maml::MetaTask;
use uavmeta_proto::config::Config;
use uavmeta_proto::dataset::{split, Transition};
use uavmeta_world::heuristics::EpsilonPolicy;

/// `collect.transitions` transitions of task `name`, drawn from `seed`.
pub fn transitions(config: &Config, name: &str, seed: u64) -> Vec<Transition> {
    let task = config.task(name).unwrap();
    let mut data = Vec::new();
    Collector::new(
        &config.world,
        task,
        0,
        0,
        Box::new(EpsilonPolicy::new(0.1, seed)),
        seed,
    )
    .fill(config.collect.transitions, &mut data);
    data
}

/// `set` encoded for the config's world.
pub fn encode(config: &Config, set: &[Transition]) -> Transitions {
    Transitions::new(set, &config.world, config.learner.reward_scale).unwrap()
}

/// Task `name`'s transitions split into support and query sets.
pub fn meta_task(config: &Config, name: &str, seed: u64) -> MetaTask {
    let data = transitions(config, name, seed);
    let (support, query) = split(&data, config.meta.support_fraction, seed).unwrap();
    MetaTask {
        name: name.to_string(),
        support: encode(config, &support),
        query: encode(config, &query),
    }
}
