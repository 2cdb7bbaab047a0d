//! Running policies in the world: one episode, or an evaluation.
//!
//! docs/MODEL.md section 5, "Evaluation": the world is deterministic given the start cell unless
//! its rain moves, so the exact expected return of a deterministic policy under a uniform start is
//! the mean over all L^2 start cells. [`evaluation_worlds`] therefore gives one episode per start
//! cell on such a world (one in all if the config fixes the start), and Monte-Carlo episodes only
//! where the rain moves: there the i-th episode of an evaluation with seed S runs in the world
//! seeded by [`episode_seed`]`(S, i)`, so every method evaluated with the same seed meets the same
//! start cells and rain moves. [`rollout`] always runs Monte-Carlo episodes, as `uavmeta env
//! rollout --episodes N --seed S` asks.

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::Serialize;
use uavmeta_proto::config::{
    enumerated_starts, TaskConfig, WorldConfig, MAX_JOINT_STARTS, MAX_UAVS,
};
use uavmeta_proto::dataset::Transition;
use uavmeta_proto::stats::{EpisodeMetrics, PolicyMetrics};

use crate::world::{Move, Step, World};

/// Chooses an action index `move * targets + target` for the world's current state. Heuristics
/// may read the whole world; learned policies read only `world.observation()`.
pub trait Policy {
    fn act(&mut self, world: &World) -> usize;

    /// Every UAV's action, UAV u's into `actions[u]` (docs/MODEL.md section 11): by default one
    /// [`Policy::act`] a UAV, in UAV order, which is a team policy only for a policy whose
    /// actions do not depend on which UAV asks (random, replayed); others override this.
    fn act_team(&mut self, world: &World, actions: &mut [usize]) {
        actions.iter_mut().for_each(|a| *a = self.act(world));
    }

    /// Whether [`Policy::act_team`] acts for a team of any size; a policy of one UAV (a learned
    /// network, the planner) acts for the one UAV there is.
    fn acts_for_teams(&self) -> bool {
        false
    }
}

/// One UAV's part of a team's step: its cell before the move, its action, move and target.
#[derive(Debug, Clone, Copy, Serialize)]
pub struct UavStepRecord {
    pub position: (u32, u32),
    pub action: usize,
    #[serde(rename = "move")]
    pub mv: Move,
    pub device: usize,
}

impl UavStepRecord {
    fn of(world: &World, position: (u32, u32), action: usize) -> Self {
        let (mv, device) = world.layout().split(action);
        let mv = Move::from_index(mv);
        Self {
            position,
            action,
            mv,
            device,
        }
    }
}

/// One step as `--trace` prints it; in a team, UAV 0's cell, action, move and target beside the
/// team's reward, power and outages, and every UAV's in `uavs`.
#[derive(Debug, Clone, Copy, Serialize)]
pub struct StepRecord<'a> {
    /// Step index within the episode, from 0.
    pub t: u32,
    /// The UAV's cell before the move.
    pub position: (u32, u32),
    pub action: usize,
    #[serde(rename = "move")]
    pub mv: Move,
    /// The target served: a device, or K for none.
    pub device: usize,
    pub reward: f64,
    pub power_mw: f64,
    pub outage: bool,
    /// A_1..A_K after the AoI update.
    pub aoi: &'a [u16],
    /// In a team (`world.uavs` > 1), each UAV's part, UAV order; absent for one UAV.
    #[serde(skip_serializing_if = "<[_]>::is_empty")]
    pub uavs: &'a [UavStepRecord],
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
    let mut tally = EpisodeTally::default();
    let uavs = world.uavs();
    let mut team = [0usize; MAX_UAVS];
    let actions = &mut team[..uavs];
    let mut cells = [(0, 0); MAX_UAVS];
    let mut parts = [UavStepRecord::of(world, (0, 0), 0); MAX_UAVS];
    loop {
        let t = world.t();
        (0..uavs).for_each(|u| cells[u] = world.uav_cell(u));
        policy.act_team(world, actions);
        let step = world.step_team(actions);
        for u in 0..uavs {
            parts[u] = UavStepRecord::of(world, cells[u], actions[u]);
        }
        let first = parts[0];
        observe(&StepRecord {
            t,
            position: first.position,
            action: first.action,
            mv: first.mv,
            device: first.device,
            reward: step.reward,
            power_mw: step.power_mw,
            outage: step.outages > 0,
            aoi: world.aoi(),
            uavs: if uavs > 1 { &parts[..uavs] } else { &[] },
        });
        tally.add(&step);
        if step.truncated {
            break;
        }
    }
    tally.finish()
}

/// An episode's metrics as its steps come in: sums, and per-step means at the end.
#[derive(Debug, Clone, Copy, Default)]
pub struct EpisodeTally {
    sums: EpisodeMetrics,
    steps: u32,
}

impl EpisodeTally {
    pub fn add(&mut self, step: &Step) {
        self.sums.ret += step.reward;
        self.sums.aoi += step.aoi_mean;
        self.sums.power_mw += step.power_mw;
        self.sums.outages += step.outages;
        self.steps += 1;
    }

    /// The return and outages summed, AoI and power averaged over the steps taken.
    pub fn finish(self) -> EpisodeMetrics {
        EpisodeMetrics {
            aoi: self.sums.aoi / self.steps as f64,
            power_mw: self.sums.power_mw / self.steps as f64,
            ..self.sums
        }
    }
}

/// Takes `action` in `world` and returns the transition an actor records: s(t), a, r, s(t+1),
/// t, and whether the horizon truncates the episode. Its ids (task, actor, episode, seq) are 0,
/// for the caller to set.
pub fn record_step(world: &mut World, action: usize) -> Transition {
    let (step, obs) = (world.t(), world.observation().to_vec());
    let outcome = world.step(action);
    Transition {
        task: 0,
        actor: 0,
        episode: 0,
        step,
        seq: 0,
        obs,
        // Below 5K <= 5 * MAX_DEVICES, checked by the world's step.
        action: action as u16,
        reward: outcome.reward as f32,
        next_obs: world.observation().to_vec(),
        truncated: outcome.truncated,
    }
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
    observe: impl FnMut(usize, &StepRecord<'_>),
) -> Vec<EpisodeMetrics> {
    run_worlds(
        episode_worlds(world_cfg, task, episodes, seed),
        policy,
        observe,
    )
}

/// Runs one episode of `policy` in each of `worlds`, handing each step with its episode index
/// to `observe`.
pub fn run_worlds(
    worlds: impl IntoIterator<Item = World>,
    policy: &mut dyn Policy,
    mut observe: impl FnMut(usize, &StepRecord<'_>),
) -> Vec<EpisodeMetrics> {
    worlds
        .into_iter()
        .enumerate()
        .map(|(i, mut world)| run_episode_observed(&mut world, policy, |step| observe(i, step)))
        .collect()
}

/// The worlds of episodes 0..episodes of an evaluation seeded `seed`, in order: clones of one
/// world (sharing its power tables), world i reseeded with `episode_seed(seed, i)`, so that its
/// next reset starts episode i. Every evaluation path builds its episodes here.
pub fn episode_worlds(
    world_cfg: &WorldConfig,
    task: &TaskConfig,
    episodes: usize,
    seed: u64,
) -> impl Iterator<Item = World> {
    let template = World::new(world_cfg, task, seed);
    (0..episodes).map(move |i| {
        let mut world = template.clone();
        world.reseed(episode_seed(seed, i));
        world
    })
}

/// The worlds of one evaluation, each ready for its episode (every path that scores a policy
/// builds them here), charging the risky region's expected penalty: on a deterministic world one
/// per start ([`start_worlds`]), whatever `episodes`; where the rain moves, `episodes`
/// Monte-Carlo worlds of [`episode_worlds`].
pub fn evaluation_worlds(
    world_cfg: &WorldConfig,
    task: &TaskConfig,
    episodes: usize,
    seed: u64,
) -> Vec<World> {
    let template = World::new(world_cfg, task, seed).expecting_risk();
    if !template.is_deterministic() {
        let worlds = episode_worlds(world_cfg, task, episodes, seed);
        return worlds.map(World::expecting_risk).collect();
    }
    start_worlds(&template)
}

/// The seed of the fixed sample of joint start cells, the same for every method and task.
pub const JOINT_START_SEED: u64 = 0x7ea3_5eed;

/// A deterministic world `template` from each start: every cell of the grid (each of a team's
/// joint start cells), or its fixed start cell alone. Exact evaluation runs one episode in each.
pub fn start_worlds(template: &World) -> Vec<World> {
    if template.start_cell().is_some() {
        return vec![template.clone()];
    }
    let grid = template.grid_cells();
    if template.uavs() == 1 {
        return (0..grid * grid)
            .map(|c| template.clone().with_start((c % grid, c / grid)))
            .collect();
    }
    joint_starts(grid, template.uavs())
        .iter()
        .map(|starts| template.clone().with_starts(starts))
        .collect()
}

/// Every joint start cell of `uavs` UAVs on a `grid` a side, UAV 0's cell slowest, or
/// [`MAX_JOINT_STARTS`] of them drawn uniformly from [`JOINT_START_SEED`] where there are more.
fn joint_starts(grid: u32, uavs: usize) -> Vec<Vec<(u32, u32)>> {
    let cells = grid as usize * grid as usize;
    let cell = |c: usize| ((c % grid as usize) as u32, (c / grid as usize) as u32);
    match enumerated_starts(cells, uavs) {
        Some(n) => (0..n)
            .map(|i| {
                let digit = |u: usize| i / cells.pow((uavs - 1 - u) as u32) % cells;
                (0..uavs).map(|u| cell(digit(u))).collect()
            })
            .collect(),
        None => {
            let mut rng = ChaCha8Rng::seed_from_u64(JOINT_START_SEED);
            (0..MAX_JOINT_STARTS)
                .map(|_| {
                    (0..uavs)
                        .map(|_| cell(rng.random_range(0..cells)))
                        .collect()
                })
                .collect()
        }
    }
}

/// Evaluation of `policy` on `task` over [`evaluation_worlds`]: exact over every start cell where
/// the world is deterministic, `episodes` fixed Monte-Carlo episodes where the rain moves.
pub fn evaluate(
    world_cfg: &WorldConfig,
    task: &TaskConfig,
    policy: &mut dyn Policy,
    episodes: usize,
    seed: u64,
) -> PolicyMetrics {
    PolicyMetrics::from_episodes(&evaluate_episodes(world_cfg, task, policy, episodes, seed))
}

/// The episodes of [`evaluate`], one per evaluation world.
pub fn evaluate_episodes(
    world_cfg: &WorldConfig,
    task: &TaskConfig,
    policy: &mut dyn Policy,
    episodes: usize,
    seed: u64,
) -> Vec<EpisodeMetrics> {
    evaluation_worlds(world_cfg, task, episodes, seed)
        .iter_mut()
        .map(|world| run_episode(world, policy))
        .collect()
}

/// One episode's path through the grid, for drawing.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Trajectory {
    /// The UAV's cell at t = 0..=horizon: the start cell, then the cell after every move.
    pub cells: Vec<(u32, u32)>,
    pub metrics: EpisodeMetrics,
}

/// Runs `policy` for the first episode of an evaluation seeded `seed` (the episode
/// [`evaluate`] runs first) and records where the UAV flew.
pub fn record_trajectory(
    world_cfg: &WorldConfig,
    task: &TaskConfig,
    policy: &mut dyn Policy,
    seed: u64,
) -> Trajectory {
    let mut world = episode_worlds(world_cfg, task, 1, seed)
        .next()
        .expect("episode_worlds yields one world per episode");
    let mut cells = Vec::with_capacity(world.horizon() as usize + 1);
    let metrics = run_episode_observed(&mut world, policy, |step| cells.push(step.position));
    cells.push(world.uav());
    Trajectory { cells, metrics }
}

#[cfg(test)]
mod tests {
    use uavmeta_proto::config::{Config, RainZone};

    use super::*;
    use crate::heuristics::RandomPolicy;

    #[test]
    fn trajectory_is_the_first_evaluation_episode() {
        let config = Config::default();
        let task = TaskConfig {
            rain_moves_every: Some(7),
            ..TaskConfig::one_off(
                300.0,
                Some(RainZone {
                    x0: 2,
                    y0: 2,
                    x1: 5,
                    y1: 6,
                }),
            )
        };
        let trajectory = record_trajectory(&config.world, &task, &mut RandomPolicy::new(4), 11);

        assert_eq!(trajectory.cells.len(), config.world.horizon as usize + 1);
        for pair in trajectory.cells.windows(2) {
            let (a, b) = (pair[0], pair[1]);
            assert!(a.0.abs_diff(b.0) + a.1.abs_diff(b.1) <= 1, "{a:?} -> {b:?}");
        }
        let grid = config.world.grid_cells;
        assert!(trajectory.cells.iter().all(|&(x, y)| x < grid && y < grid));
        // A random policy on a 10 x 10 grid does not hover for a whole episode.
        assert!(trajectory.cells.iter().any(|&c| c != trajectory.cells[0]));

        let mut positions = vec![];
        let episodes = rollout(
            &config.world,
            &task,
            &mut RandomPolicy::new(4),
            1,
            11,
            |_, step| positions.push(step.position),
        );
        assert_eq!(trajectory.metrics, episodes[0]);
        assert_eq!(positions, trajectory.cells[..positions.len()]);
    }
}
