//! Running policies in the world: one episode, or a Monte-Carlo evaluation over fixed episodes.
//!
//! The i-th episode of an evaluation with seed S always runs in the world seeded by
//! [`episode_seed`]`(S, i)`, so every method evaluated with the same seed meets the same start
//! cells and rain moves.

use serde::Serialize;
use uavmeta_proto::config::{TaskConfig, WorldConfig};
use uavmeta_proto::stats::{EpisodeMetrics, PolicyMetrics};

use crate::world::{Move, World};

/// Chooses an action index `move * K + device` for the world's current state. Heuristics may read
/// the whole world; learned policies read only `world.observation()`.
pub trait Policy {
    fn act(&mut self, world: &World) -> usize;
}

/// One step as `--trace` prints it.
#[derive(Debug, Clone, Copy, Serialize)]
pub struct StepRecord<'a> {
    /// Step index within the episode, from 0.
    pub t: u32,
    /// The UAV's cell before the move.
    pub position: (u32, u32),
    pub action: usize,
    #[serde(rename = "move")]
    pub mv: Move,
    pub device: usize,
    pub reward: f64,
    pub power_mw: f64,
    pub outage: bool,
    /// A_1..A_K after the AoI update.
    pub aoi: &'a [u16],
}

/// Resets the world and runs one episode to its horizon.
pub fn run_episode(world: &mut World, policy: &mut dyn Policy) -> EpisodeMetrics {
    run_episode_observed(world, policy, |_| {})
}

/// As [`run_episode`], handing every step to `observe`.
pub fn run_episode_observed(
    world: &mut World,
    policy: &mut dyn Policy,
    mut observe: impl FnMut(&StepRecord<'_>),
) -> EpisodeMetrics {
    world.reset();
    let mut metrics = EpisodeMetrics::default();
    let mut steps = 0u32;
    loop {
        let t = world.t();
        let position = world.uav();
        let action = policy.act(world);
        let step = world.step(action);
        observe(&StepRecord {
            t,
            position,
            action,
            mv: step.mv,
            device: step.device,
            reward: step.reward,
            power_mw: step.power_mw,
            outage: step.outage,
            aoi: world.aoi(),
        });
        metrics.ret += step.reward;
        metrics.aoi += step.aoi_mean;
        metrics.power_mw += step.power_mw;
        metrics.outages += step.outage as u32;
        steps += 1;
        if step.truncated {
            break;
        }
    }
    metrics.aoi /= steps as f64;
    metrics.power_mw /= steps as f64;
    metrics
}

/// The world seed of episode `episode` of an evaluation seeded `seed` (SplitMix64 of the pair, so
/// nearby seeds and episodes give unrelated streams).
pub fn episode_seed(seed: u64, episode: usize) -> u64 {
    let mut z = seed ^ (episode as u64).wrapping_mul(0x9e37_79b9_7f4a_7c15);
    z = z.wrapping_add(0x9e37_79b9_7f4a_7c15);
    z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    z ^ (z >> 31)
}

/// Runs `episodes` episodes of `policy` on `task`, episode i in the world of
/// `episode_seed(seed, i)`, handing each step with its episode index to `observe`.
pub fn rollout(
    world_cfg: &WorldConfig,
    task: &TaskConfig,
    policy: &mut dyn Policy,
    episodes: usize,
    seed: u64,
    mut observe: impl FnMut(usize, &StepRecord<'_>),
) -> Vec<EpisodeMetrics> {
    let mut world = World::new(world_cfg, task, seed);
    (0..episodes)
        .map(|i| {
            world.reseed(episode_seed(seed, i));
            run_episode_observed(&mut world, policy, |step| observe(i, step))
        })
        .collect()
}

/// Monte-Carlo evaluation of `policy` on `task` over `episodes` fixed episodes.
pub fn evaluate(
    world_cfg: &WorldConfig,
    task: &TaskConfig,
    policy: &mut dyn Policy,
    episodes: usize,
    seed: u64,
) -> PolicyMetrics {
    PolicyMetrics::from_episodes(&rollout(world_cfg, task, policy, episodes, seed, |_, _| {}))
}
