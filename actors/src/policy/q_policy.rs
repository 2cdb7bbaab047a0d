//! A Q-network acting in the world: its greedy policy, and the evaluator that scores it on the true
//! environment for `uavmeta_learner::train` (SPEC section 5, "Evaluation").
//!
//! The evaluator runs the same episodes as [`crate::rollout::evaluate`] with a [`QPolicy`] (every
//! start cell of a deterministic world, Monte-Carlo episodes where the rain moves), but steps all
//! of them in lockstep (every episode lasts the horizon) so that each step is one forward pass
//! over an `[episodes, D]` batch rather than `episodes` passes over one row.

use tch::Tensor;
use uavmeta_learner::qnet::QNetwork;
use uavmeta_learner::train::EvaluatePolicy;
use uavmeta_proto::config::{Config, TaskConfig, WorldConfig};
use uavmeta_proto::stats::{EpisodeMetrics, PolicyMetrics};

use crate::rollout::{evaluation_worlds, EpisodeTally, Policy};
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

/// Evaluation of greedy Q-policies on one task, always over the same episodes
/// ([`crate::rollout::evaluation_worlds`]).
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

impl Evaluator {
    /// Each evaluation episode of `q`'s greedy policy: its start cell `(x, y)` and its metrics, in
    /// the order of [`evaluation_worlds`].
    pub fn episodes(&self, q: &QNetwork) -> Vec<((u16, u16), EpisodeMetrics)> {
        let mut worlds = evaluation_worlds(&self.world, &self.task, self.episodes, self.seed);
        if worlds.is_empty() {
            return Vec::new();
        }
        worlds.iter_mut().for_each(World::reset);
        let starts: Vec<(u16, u16)> = worlds
            .iter()
            .map(|w| (w.observation()[0], w.observation()[1]))
            .collect();
        let (e, d) = (worlds.len(), q.obs_len());
        let mut obs = vec![0f32; e * d];
        let mut actions = vec![0i64; e];
        let mut tallies = vec![EpisodeTally::default(); e];
        for _ in 0..self.world.horizon {
            for (world, row) in worlds.iter().zip(obs.chunks_exact_mut(d)) {
                world.write_normalised(row);
            }
            let batch = Tensor::from_slice(&obs).view([e as i64, d as i64]); // [E, D]
            q.greedy(&batch).copy_data(&mut actions, e); // [E]
            for ((world, &action), tally) in worlds.iter_mut().zip(&actions).zip(&mut tallies) {
                tally.add(&world.step(action as usize));
            }
        }
        starts
            .into_iter()
            .zip(tallies.into_iter().map(EpisodeTally::finish))
            .collect()
    }
}

impl EvaluatePolicy for Evaluator {
    fn evaluate(&mut self, q: &QNetwork) -> PolicyMetrics {
        let episodes: Vec<EpisodeMetrics> = self.episodes(q).into_iter().map(|(_, m)| m).collect();
        PolicyMetrics::from_episodes(&episodes)
    }
}

#[cfg(test)]
mod tests {
    use uavmeta_proto::config::{Config, RainZone};

    use super::*;
    use crate::rollout::evaluate;
    use uavmeta_learner::qnet::QNetworkConfig;

    fn assert_metrics_close(batched: &PolicyMetrics, single: &PolicyMetrics) {
        assert_eq!(batched.episodes, single.episodes);
        let pairs = [
            (batched.ret, single.ret),
            (batched.aoi, single.aoi),
            (batched.power_mw, single.power_mw),
            (batched.outages, single.outages),
        ];
        for (b, s) in pairs {
            assert!(
                (b.mean - s.mean).abs() <= 1e-9 && (b.ci95 - s.ci95).abs() <= 1e-9,
                "batched {batched:?}\nsingle  {single:?}"
            );
        }
    }

    /// The lockstep evaluation runs exactly the episodes of `rollout::evaluate` with a `QPolicy`:
    /// on a clear task and on a rain task whose zone moves (so the worlds' random streams matter).
    #[test]
    fn batched_evaluation_equals_episode_by_episode() {
        tch::set_num_threads(1);
        let config = Config::default();
        let rain = TaskConfig {
            rain_moves_every: Some(10),
            ..TaskConfig::one_off(
                300.0,
                Some(RainZone {
                    x0: 3,
                    y0: 3,
                    x1: 6,
                    y1: 6,
                }),
            )
        };
        let tasks = [TaskConfig::one_off(100.0, None), rain];
        let (obs_len, actions) = (config.world.observation_len(), config.world.action_count());
        for (net_seed, task) in tasks.iter().enumerate() {
            let q =
                QNetworkConfig::new(obs_len, actions, &config.learner.hidden).init(net_seed as u64);
            for episodes in [1, 7] {
                let seed = 31 + episodes as u64;
                let batched = Evaluator::new(&config.world, task, episodes, seed).evaluate(&q);
                let single = evaluate(&config.world, task, &mut QPolicy::new(&q), episodes, seed);
                // Every start cell on the clear task; the Monte-Carlo episodes where rain moves.
                let expected = if task.rain_moves_every.is_some() {
                    episodes
                } else {
                    100
                };
                assert_eq!(batched.episodes, expected);
                assert_metrics_close(&batched, &single);
                // The rain task's episodes do fly through rain, so outages are compared too.
                assert_eq!(single.outages.mean > 0.0, task.rain.is_some());
            }
        }
    }
}
