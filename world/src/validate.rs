//! Whether a transition is one this world could have made: what the store checks before it
//! appends a batch, and `uavmeta dataset inspect` checks in a file.
//!
//! The checks, in order, each named by the `reason` label it counts under
//! (`uavmeta_proto::metrics::store::REJECTION_REASONS`):
//! - `non_finite`: the reward is a finite number;
//! - `action`: a below the action count (5K, or 5(K + 1) with the idle target);
//! - `step`: the step index is below the horizon T, and `truncated` is set exactly on step T - 1;
//! - `position`: both cells are on the grid, and at step 0 the UAV is at the fixed start cell if
//!   the world has one;
//! - `aoi`: every AoI of s(t) and s(t+1) is in [1, aoi_max], and in s(t) at most step + 1 (every
//!   counter starts at 1 and ages by one a step);
//! - `reward` and `next_state`: the world is deterministic given (s, a) and the task, except for
//!   the outage and the risky region's penalty, one of [`World::possible_outages`] and of
//!   [`World::possible_penalties`]; the transition must be the world's
//!   step from s(t) under a for one of them: the same s(t+1), and the same reward as the f32 the
//!   actors write (`step.reward as f32`), exactly.

use std::fmt;

use uavmeta_proto::config::{TaskConfig, WorldConfig};
use uavmeta_proto::dataset::Transition;
use uavmeta_proto::layout::Layout;
use uavmeta_proto::metrics::store::{ACTION, AOI, NEXT_STATE, NON_FINITE, POSITION, REWARD, STEP};
use uavmeta_proto::payload::TransitionSlot;

use crate::world::World;

/// The parts of a transition the checks read, borrowed from a shared-memory slot or a dataset
/// transition without copying.
#[derive(Debug, Clone, Copy)]
pub struct Claimed<'a> {
    pub step: u32,
    pub obs: &'a [u16],
    pub action: u16,
    pub reward: f32,
    pub next_obs: &'a [u16],
    pub truncated: bool,
}

impl<'a> Claimed<'a> {
    /// A slot of a batch whose header says `obs_len` entries are used (checked by the caller
    /// against the config, so at most the slot's capacity).
    pub fn from_slot(slot: &'a TransitionSlot, obs_len: usize) -> Self {
        Self {
            step: slot.step,
            obs: &slot.obs[..obs_len],
            action: slot.action,
            reward: slot.reward,
            next_obs: &slot.next_obs[..obs_len],
            truncated: slot.truncated != 0,
        }
    }
}

impl<'a> From<&'a Transition> for Claimed<'a> {
    fn from(t: &'a Transition) -> Self {
        Self {
            step: t.step,
            obs: &t.obs,
            action: t.action,
            reward: t.reward,
            next_obs: &t.next_obs,
            truncated: t.truncated,
        }
    }
}

/// Why a transition is not one this world makes: the check it failed (a metric label) and what
/// was found against what was expected.
#[derive(Debug, Clone, PartialEq)]
pub struct Rejection {
    /// One of `uavmeta_proto::metrics::store::REJECTION_REASONS`.
    pub reason: &'static str,
    pub detail: String,
}

impl fmt::Display for Rejection {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{} ({})", self.detail, self.reason)
    }
}

fn reject(reason: &'static str, detail: String) -> Result<(), Rejection> {
    Err(Rejection { reason, detail })
}

/// Checks transitions against one task's world; holds a scratch state, so a check allocates
/// nothing.
#[derive(Debug, Clone)]
pub struct Validator {
    world: World,
    next: Vec<u16>,
}

impl Validator {
    /// The checks of `task` in `world` (a config that passed `Config::validate`).
    pub fn new(world: &WorldConfig, task: &TaskConfig) -> Self {
        Self::of(World::new(world, task, 0))
    }

    /// The checks of every task in `tasks`, in order, the tasks on the world's layout sharing
    /// one world's power tables (a task with a layout of its own has its own).
    pub fn for_tasks(world: &WorldConfig, tasks: &[TaskConfig]) -> Vec<Self> {
        let mut shared: Option<World> = None;
        let mut of_task = |task: &TaskConfig| {
            if task.device_cells.is_some() || task.layout_seed.is_some() {
                return World::new(world, task, 0);
            }
            let template = shared.get_or_insert_with(|| World::new(world, task, 0));
            template.with_task(task)
        };
        tasks.iter().map(|task| Self::of(of_task(task))).collect()
    }

    fn of(world: World) -> Self {
        let next = vec![0; 2 + world.devices()];
        Self { world, next }
    }

    /// Every check of the module doc, the first that fails named.
    pub fn check(&mut self, t: Claimed<'_>) -> Result<(), Rejection> {
        self.check_ranges(&t)?;
        self.check_outcome(&t)
    }

    /// The checks that need no step of the world: finite, in range, consistent with the step
    /// index.
    fn check_ranges(&self, t: &Claimed<'_>) -> Result<(), Rejection> {
        let w = &self.world;
        if !t.reward.is_finite() {
            return reject(NON_FINITE, format!("reward {}", t.reward));
        }
        if usize::from(t.action) >= w.layout().action_count() {
            let detail = format!(
                "action {}, expected below the action count, 5 moves x targets = {}",
                t.action,
                w.layout().action_count()
            );
            return reject(ACTION, detail);
        }
        let horizon = w.horizon();
        if t.step >= horizon || t.truncated != (t.step + 1 == horizon) {
            let detail = format!(
                "step {} with truncated = {}, expected a step below the horizon {horizon}, \
                 truncated exactly on step {}",
                t.step,
                t.truncated,
                horizon - 1
            );
            return reject(STEP, detail);
        }
        let expected_len = 2 + w.devices();
        if t.obs.len() != expected_len || t.next_obs.len() != expected_len {
            let detail = format!(
                "observations of {} and {} values, expected 2 + K = {expected_len}",
                t.obs.len(),
                t.next_obs.len()
            );
            return reject(POSITION, detail);
        }
        self.check_cells(t)?;
        self.check_aoi(t)
    }

    fn check_cells(&self, t: &Claimed<'_>) -> Result<(), Rejection> {
        let grid = self.world.grid_cells();
        for (field, s) in [("s(t)", t.obs), ("s(t+1)", t.next_obs)] {
            if u32::from(s[0]) >= grid || u32::from(s[1]) >= grid {
                let detail = format!(
                    "{field} at cell ({}, {}), expected both below grid_cells = {grid}",
                    s[0], s[1]
                );
                return reject(POSITION, detail);
            }
        }
        let (x, y) = Layout::cell(t.obs);
        let at = (u32::from(x), u32::from(y));
        match self.world.start_cell() {
            Some(start) if t.step == 0 && at != start => reject(
                POSITION,
                format!("step 0 at cell {at:?}, expected the start cell {start:?}"),
            ),
            _ => Ok(()),
        }
    }

    fn check_aoi(&self, t: &Claimed<'_>) -> Result<(), Rejection> {
        let cap = self.world.aoi_max();
        let reachable = t.step.saturating_add(1).min(u32::from(cap));
        for (field, s, top) in [
            ("s(t)", t.obs, reachable),
            ("s(t+1)", t.next_obs, u32::from(cap)),
        ] {
            if let Some(&a) = s[2..].iter().find(|&&a| a == 0 || u32::from(a) > top) {
                let detail = format!(
                    "{field} has an AoI of {a} at step {}, expected 1 to {top} (aoi_max = {cap})",
                    t.step
                );
                return reject(AOI, detail);
            }
        }
        Ok(())
    }

    /// The world's step from s(t) under a, for every outage it allows, must give s(t+1) and the
    /// reward.
    fn check_outcome(&mut self, t: &Claimed<'_>) -> Result<(), Rejection> {
        let (x, y) = Layout::cell(t.obs);
        let (x, y) = (u32::from(x), u32::from(y));
        let mut wrong_reward = None;
        let action = usize::from(t.action);
        let target = self.world.layout().device(action);
        let penalties = self.world.possible_penalties(x, y, target);
        let cases = self.world.possible_outages(x, y, t.step).iter();
        for (&outage, &penalised) in cases.flat_map(|o| penalties.iter().map(move |p| (o, p))) {
            let next = &mut self.next;
            let Some(reward) = self.world.outcome(t.obs, action, outage, penalised, next) else {
                return reject(
                    POSITION,
                    format!("s(t) = {:?} is no state of this world", t.obs),
                );
            };
            if self.next != t.next_obs {
                continue;
            }
            if reward as f32 == t.reward {
                return Ok(());
            }
            wrong_reward = Some(reward as f32);
        }
        match wrong_reward {
            Some(expected) => reject(
                REWARD,
                format!("reward {}, the world gives {expected}", t.reward),
            ),
            None => reject(
                NEXT_STATE,
                format!(
                    "s(t+1) = {:?} after action {} from {:?}, the world gives {:?}",
                    t.next_obs, t.action, t.obs, self.next
                ),
            ),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rollout::episode_seed;
    use uavmeta_proto::config::{Config, RainZone};

    /// A few episodes of `task` under a seeded random policy, as actors write them.
    fn episodes(config: &Config, task: &TaskConfig) -> Vec<Transition> {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        let mut world = World::new(&config.world, task, 0);
        let mut out = Vec::new();
        for episode in 0..3 {
            world.reseed(episode_seed(0, episode));
            world.reset();
            loop {
                let obs = world.observation().to_vec();
                let step_index = world.t();
                let action = rng.random_range(0..world.layout().action_count());
                let step = world.step(action);
                out.push(Transition {
                    task: 0,
                    actor: 0,
                    episode: episode as u64,
                    step: step_index,
                    seq: out.len() as u64,
                    obs,
                    action: action as u16,
                    reward: step.reward as f32,
                    next_obs: world.observation().to_vec(),
                    truncated: step.truncated,
                });
                if step.truncated {
                    break;
                }
            }
        }
        out
    }

    fn rainy(every: Option<u32>) -> Config {
        let mut config = Config::default();
        config.world.horizon = 40;
        config.tasks[0].rain = Some(RainZone {
            x0: 2,
            y0: 2,
            x1: 6,
            y1: 6,
        });
        config.tasks[0].rain_moves_every = every;
        config
    }

    #[test]
    fn every_step_the_world_makes_passes_with_fixed_and_moving_rain() {
        for config in [Config::default(), rainy(None), rainy(Some(5))] {
            let task = &config.tasks[0];
            let steps = episodes(&config, task);
            assert!(steps.len() >= 3 * config.world.horizon as usize);
            let mut validator = Validator::new(&config.world, task);
            for t in &steps {
                validator
                    .check(t.into())
                    .unwrap_or_else(|r| panic!("{t:?}: {r}"));
            }
        }
    }

    fn first_failure(config: &Config, change: impl Fn(&mut Transition)) -> Rejection {
        let task = &config.tasks[0];
        let mut t = episodes(config, task)[7].clone();
        change(&mut t);
        Validator::new(&config.world, task)
            .check((&t).into())
            .expect_err("must be rejected")
    }

    #[test]
    fn validators_sharing_one_worlds_tables_check_each_task_as_its_own_world() {
        let mut config = rainy(None);
        config.tasks[1].rain = None;
        // A task with a layout of its own is checked in its own world, not the shared one.
        config.tasks[2].layout_seed = Some(99);
        let mut shared = Validator::for_tasks(&config.world, &config.tasks);
        for (i, task) in config.tasks.iter().enumerate().take(3) {
            let mut own = Validator::new(&config.world, task);
            for t in &episodes(&config, task) {
                assert_eq!(shared[i].check(t.into()), Ok(()));
                assert_eq!(own.check(t.into()), Ok(()));
            }
        }
        // lambda differs between tasks: one task's steps fail another's reward check.
        let steps = episodes(&config, &config.tasks[2]);
        let failed = steps
            .iter()
            .filter(|t| shared[1].check((*t).into()).is_err());
        assert!(failed.count() > 0);
    }

    #[test]
    fn each_kind_of_bad_transition_is_named() {
        let config = rainy(None);
        type Corrupt = Box<dyn Fn(&mut Transition)>;
        let cases: [(&str, Corrupt); 9] = [
            (NON_FINITE, Box::new(|t| t.reward = f32::NAN)),
            (NON_FINITE, Box::new(|t| t.reward = f32::INFINITY)),
            (ACTION, Box::new(|t| t.action = 9999)),
            (POSITION, Box::new(|t| t.obs[0] = 65535)),
            (AOI, Box::new(|t| t.obs[3] = 0)),
            (AOI, Box::new(|t| t.next_obs[2] = 65535)),
            (STEP, Box::new(|t| t.truncated = true)),
            (REWARD, Box::new(|t| t.reward = 1e30)),
            (
                NEXT_STATE,
                Box::new(|t| t.next_obs[0] = (t.next_obs[0] + 1) % 10),
            ),
        ];
        for (reason, change) in cases {
            let rejection = first_failure(&config, change);
            assert_eq!(rejection.reason, reason, "{rejection}");
        }
    }

    #[test]
    fn a_reward_off_by_one_unit_in_the_last_place_is_rejected() {
        let config = Config::default();
        let rejection = first_failure(&config, |t| {
            t.reward = f32::from_bits(t.reward.to_bits() + 1);
        });
        assert_eq!(rejection.reason, REWARD, "{rejection}");
        assert!(rejection.detail.contains("the world gives"), "{rejection}");
    }
}
