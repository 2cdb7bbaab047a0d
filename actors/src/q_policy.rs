//! A Q-network acting in the world: its greedy policy, and the evaluator that scores it on the true
//! environment for `uavmeta_learner::train` (SPEC section 5, "Evaluation").

use tch::Tensor;
use uavmeta_learner::qnet::QNetwork;
use uavmeta_learner::train::EvaluatePolicy;
use uavmeta_proto::config::{Config, TaskConfig, WorldConfig};
use uavmeta_proto::stats::PolicyMetrics;

use crate::rollout::{evaluate, Policy};
use crate::world::World;

/// `argmax_a Q(s, a)` on the normalised observation.
pub struct QPolicy<'a> {
    q: &'a QNetwork,
    /// The normalised observation, reused every step.
    obs: Vec<f32>,
}

impl<'a> QPolicy<'a> {
    pub fn new(q: &'a QNetwork) -> Self {
        Self {
            q,
            obs: vec![0.0; q.obs_len()],
        }
    }
}

impl Policy for QPolicy<'_> {
    fn act(&mut self, world: &World) -> usize {
        world.write_normalised(&mut self.obs);
        let obs = Tensor::from_slice(&self.obs).view([1, self.obs.len() as i64]); // [1, D]
        self.q.greedy(&obs).int64_value(&[0]) as usize
    }
}

/// Monte-Carlo evaluation of greedy Q-policies on one task, always over the same episodes.
#[derive(Debug, Clone)]
pub struct Evaluator {
    world: WorldConfig,
    task: TaskConfig,
    episodes: usize,
    seed: u64,
}

impl Evaluator {
    pub fn new(world: &WorldConfig, task: &TaskConfig, episodes: usize, seed: u64) -> Self {
        Self {
            world: world.clone(),
            task: task.clone(),
            episodes,
            seed,
        }
    }

    /// The evaluator a config asks for: `learner.eval_episodes` episodes seeded `learner.eval_seed`.
    pub fn from_config(config: &Config, task: &TaskConfig) -> Self {
        Self::new(
            &config.world,
            task,
            config.learner.eval_episodes,
            config.learner.eval_seed,
        )
    }
}

impl EvaluatePolicy for Evaluator {
    fn evaluate(&mut self, q: &QNetwork) -> PolicyMetrics {
        evaluate(
            &self.world,
            &self.task,
            &mut QPolicy::new(q),
            self.episodes,
            self.seed,
        )
    }
}
