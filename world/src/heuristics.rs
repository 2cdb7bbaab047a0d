//! Heuristic behaviour policies: the baselines that calibrate every learning curve, and the
//! `--policy` parser that names them.
//!
//! - [`RandomPolicy`]: uniform over the actions.
//! - [`StalestPolicy`]: serve the device with the largest delta_k A_k, fly towards it.
//! - [`GreedyPolicy`]: serve the device that makes this step cheapest, fly towards the stalest.
//! - [`EpsilonPolicy`]: stalest (or another policy), with a uniform random action with probability P.
//! - [`ReplayPolicy`]: a fixed list of action indices read from a file.
//!
//! In a team (docs/MODEL.md section 11) the UAVs decide in order, each with a claim: stalest and
//! greedy give UAV u the best device no earlier UAV serves and fly it towards the stalest device
//! no earlier UAV flies to; random and replayed policies draw or read one action per UAV. With
//! one UAV every one of them is the paper's heuristic.
//!
//! `PolicySpec` also names the planner reference (`crate::planner`), which is no heuristic but is
//! picked the same way.

use std::fmt;
use std::path::{Path, PathBuf};
use std::str::FromStr;

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use uavmeta_proto::config::{Config, TaskConfig};
use uavmeta_proto::dataset::Transition;
use uavmeta_proto::stats::PolicyMetrics;

use crate::identify::{identify, Unidentified};
use crate::planner::PlannerPolicy;
use crate::rollout::{evaluate, Policy};
use crate::world::{Move, World};

/// A policy that cannot be parsed or built.
#[derive(Debug, thiserror::Error)]
pub enum PolicyError {
    #[error("policy `{spec}`: {expected}")]
    Spec { spec: String, expected: String },
    #[error("{path}: cannot read: {error}")]
    Read {
        path: PathBuf,
        error: std::io::Error,
    },
    #[error("{path}, line {line}: `{value}`: expected an action index below {actions}")]
    Line {
        path: PathBuf,
        line: usize,
        value: String,
        actions: usize,
    },
    #[error("{path}: holds {have} actions, but the rollout needs {need}")]
    TooShort {
        path: PathBuf,
        have: usize,
        need: usize,
    },
}

/// Uniform random actions from a seeded stream.
#[derive(Debug, Clone)]
pub struct RandomPolicy {
    rng: ChaCha8Rng,
}

impl RandomPolicy {
    pub fn new(seed: u64) -> Self {
        Self {
            rng: ChaCha8Rng::seed_from_u64(seed),
        }
    }
}

impl Policy for RandomPolicy {
    fn act(&mut self, world: &World) -> usize {
        self.rng.random_range(0..world.layout().action_count())
    }

    /// Each UAV's action drawn in turn.
    fn acts_for_teams(&self) -> bool {
        true
    }
}

/// Serve the device with the largest delta_k A_k (ties to the lowest index) and fly towards it.
#[derive(Debug, Clone, Copy, Default)]
pub struct StalestPolicy;

impl Policy for StalestPolicy {
    fn act(&mut self, world: &World) -> usize {
        one_uav(self, world)
    }

    fn acts_for_teams(&self) -> bool {
        true
    }

    fn act_team(&mut self, world: &World, actions: &mut [usize]) {
        let (mut served, mut flown) = (Claims::default(), Claims::default());
        for (u, action) in actions.iter_mut().enumerate() {
            let device = served.claim(stalest_device(world, &served));
            let goal = flown.claim(stalest_device(world, &flown));
            let mv = towards(world, world.uav_cell(u), goal);
            *action = world.layout().action(mv.index(), device);
        }
    }
}

/// Serve the device that minimises this step's cost from the current cell, a risky region's
/// expected penalty included (ties to the lowest index); fly towards the stalest device, which
/// the next steps will want to serve (in a task with a risky region, towards the nearest cell
/// outside the region it can reach).
#[derive(Debug, Clone, Copy, Default)]
pub struct GreedyPolicy;

impl Policy for GreedyPolicy {
    fn act(&mut self, world: &World) -> usize {
        one_uav(self, world)
    }

    fn acts_for_teams(&self) -> bool {
        true
    }

    fn act_team(&mut self, world: &World, actions: &mut [usize]) {
        let (mut served, mut flown) = (Claims::default(), Claims::default());
        // The targets a UAV weighs: every device, and "none" where the world has it.
        let targets = world.layout().targets();
        for (u, action) in actions.iter_mut().enumerate() {
            let cell = world.uav_cell(u);
            let target = (0..targets)
                .filter(|&k| k == world.devices() || !served.has(k))
                .map(|k| {
                    (
                        k,
                        world.cost_of_from(cell, k) + world.expected_penalty_at(cell, k),
                    )
                })
                .fold(
                    (0, f64::INFINITY),
                    |best, (k, c)| if c < best.1 { (k, c) } else { best },
                )
                .0;
            served.claim(target);
            let goal = flown.claim(stalest_device(world, &flown));
            let mv = towards_cell(world, cell, safe_cell(world, cell, goal));
            *action = world.layout().action(mv.index(), target);
        }
    }
}

/// A one-UAV world's action from a team policy.
fn one_uav(policy: &mut impl Policy, world: &World) -> usize {
    let mut action = [0];
    policy.act_team(world, &mut action);
    action[0]
}

/// Devices the earlier UAVs of a team step have claimed.
#[derive(Debug, Clone, Copy, Default)]
struct Claims(u128);

impl Claims {
    fn has(self, device: usize) -> bool {
        self.0 >> device & 1 == 1
    }

    /// Claims `device` (or K, "none", which never bars another UAV) and returns it.
    fn claim(&mut self, device: usize) -> usize {
        self.0 |= 1 << device;
        device
    }

    /// Whether every one of `devices` devices is claimed.
    fn all(self, devices: usize) -> bool {
        let mask = (1u128 << devices) - 1;
        self.0 & mask == mask
    }
}

/// Another policy with probability 1 - epsilon, uniform random with probability epsilon: `eps:P`
/// around stalest, and `q:P:FILE` around a Q-network's greedy policy.
pub struct EpsilonPolicy {
    epsilon: f64,
    coin: ChaCha8Rng,
    random: RandomPolicy,
    inner: Box<dyn Policy>,
}

impl EpsilonPolicy {
    /// Stalest with probability 1 - `epsilon` (in [0, 1]), uniform random with probability `epsilon`.
    pub fn new(epsilon: f64, seed: u64) -> Self {
        Self::around(Box::new(StalestPolicy), epsilon, seed)
    }

    /// `inner` with probability 1 - `epsilon` (in [0, 1]), uniform random with probability `epsilon`.
    pub fn around(inner: Box<dyn Policy>, epsilon: f64, seed: u64) -> Self {
        let mut coin = ChaCha8Rng::seed_from_u64(seed);
        // A stream of its own, so the coin flips do not shift the random actions.
        coin.set_stream(1);
        Self {
            epsilon,
            coin,
            random: RandomPolicy::new(seed),
            inner,
        }
    }
}

impl Policy for EpsilonPolicy {
    fn act(&mut self, world: &World) -> usize {
        if self.coin.random_bool(self.epsilon) {
            self.random.act(world)
        } else {
            self.inner.act(world)
        }
    }

    fn acts_for_teams(&self) -> bool {
        self.inner.acts_for_teams()
    }

    /// One coin a step for the whole team.
    fn act_team(&mut self, world: &World, actions: &mut [usize]) {
        if self.coin.random_bool(self.epsilon) {
            self.random.act_team(world, actions)
        } else {
            self.inner.act_team(world, actions)
        }
    }
}

/// Replays a fixed list of action indices, continuing across episodes, in a loop.
#[derive(Debug, Clone)]
pub struct ReplayPolicy {
    actions: Vec<usize>,
    next: usize,
}

impl ReplayPolicy {
    /// Replays `actions` in order.
    pub fn new(actions: Vec<usize>) -> Self {
        Self { actions, next: 0 }
    }

    /// Reads one action index per line (blank lines are skipped); each must be below
    /// `action_count`.
    pub fn from_file(path: &Path, action_count: usize) -> Result<Self, PolicyError> {
        let text = std::fs::read_to_string(path).map_err(|error| PolicyError::Read {
            path: path.to_path_buf(),
            error,
        })?;
        let actions = text
            .lines()
            .enumerate()
            .filter(|(_, line)| !line.trim().is_empty())
            .map(|(i, line)| {
                let value = line.trim();
                value
                    .parse::<usize>()
                    .ok()
                    .filter(|&a| a < action_count)
                    .ok_or_else(|| PolicyError::Line {
                        path: path.to_path_buf(),
                        line: i + 1,
                        value: value.to_string(),
                        actions: action_count,
                    })
            })
            .collect::<Result<_, _>>()?;
        Ok(Self::new(actions))
    }

    /// Actions the list holds.
    pub fn len(&self) -> usize {
        self.actions.len()
    }

    pub fn is_empty(&self) -> bool {
        self.actions.is_empty()
    }
}

impl Policy for ReplayPolicy {
    /// Past the end of the list it starts again from the first action (an actor publishing
    /// without end replays the list in a loop); [`PolicySpec::build`] refuses an empty list.
    fn act(&mut self, _world: &World) -> usize {
        let action = self.actions[self.next % self.actions.len()];
        self.next += 1;
        action
    }

    /// One action a UAV, in UAV order.
    fn acts_for_teams(&self) -> bool {
        true
    }
}

/// A behaviour policy named on the command line or in `collect.policy`.
#[derive(Debug, Clone, PartialEq)]
pub enum PolicySpec {
    Random,
    Stalest,
    Greedy,
    /// `eps:P`
    Epsilon(f64),
    /// `actions:FILE`
    Actions(PathBuf),
    /// `q:P:FILE`: the greedy policy of the Q-network checkpoint FILE (a learner's or an online
    /// agent's), with a uniform random action with probability P, as D4RL's "expert" and "medium"
    /// datasets are rollouts of one trained policy. Loading a network is the actors crate's job
    /// (`uavmeta_actors::policy::build`).
    Checkpoint {
        epsilon: f64,
        path: PathBuf,
    },
    /// `planner`: the planner reference (`crate::planner`), with the config's `[planner]`.
    Planner,
    /// `dqn-online`: an online DQN agent (`uavmeta_actors::policy::dqn_online`), which learns in the task's world
    /// and is therefore trained by `collect`, not built here.
    DqnOnline,
}

const SPEC_FORMS: &str =
    "random, stalest, greedy, planner, dqn-online, eps:P (0 <= P <= 1), q:P:CHECKPOINT or actions:FILE";

impl FromStr for PolicySpec {
    type Err = PolicyError;

    fn from_str(s: &str) -> Result<Self, PolicyError> {
        let bad = |expected: String| PolicyError::Spec {
            spec: s.to_string(),
            expected,
        };
        match s.split_once(':') {
            None => match s {
                "random" => Ok(Self::Random),
                "stalest" => Ok(Self::Stalest),
                "greedy" => Ok(Self::Greedy),
                "planner" => Ok(Self::Planner),
                "dqn-online" => Ok(Self::DqnOnline),
                _ => Err(bad(format!("expected {SPEC_FORMS}"))),
            },
            Some(("eps", p)) => match p.trim().parse::<f64>() {
                Ok(p) if (0.0..=1.0).contains(&p) => Ok(Self::Epsilon(p)),
                _ => Err(bad(format!(
                    "`{p}` is not a probability: expected eps:P with 0 <= P <= 1"
                ))),
            },
            Some(("q", rest)) => {
                let Some((p, path)) = rest.split_once(':').filter(|(_, path)| !path.is_empty())
                else {
                    return Err(bad(
                        "expected q:P:CHECKPOINT, e.g. q:0.05:runs/default/seed-0/datasets/lambda-300.uavds.agent/online-dqn".into(),
                    ));
                };
                match p.trim().parse::<f64>() {
                    Ok(epsilon) if (0.0..=1.0).contains(&epsilon) => Ok(Self::Checkpoint {
                        epsilon,
                        path: PathBuf::from(path),
                    }),
                    _ => Err(bad(format!(
                        "`{p}` is not a probability: expected q:P:CHECKPOINT with 0 <= P <= 1"
                    ))),
                }
            }
            Some(("actions", "")) => Err(bad("expected a file after `actions:`".into())),
            Some(("actions", file)) => Ok(Self::Actions(PathBuf::from(file))),
            Some(_) => Err(bad(format!("expected {SPEC_FORMS}"))),
        }
    }
}

impl fmt::Display for PolicySpec {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::Random => write!(f, "random"),
            Self::Stalest => write!(f, "stalest"),
            Self::Greedy => write!(f, "greedy"),
            Self::Planner => write!(f, "planner"),
            Self::Epsilon(p) => write!(f, "eps:{p}"),
            Self::Actions(path) => write!(f, "actions:{}", path.display()),
            Self::Checkpoint { epsilon, path } => write!(f, "q:{epsilon}:{}", path.display()),
            Self::DqnOnline => write!(f, "dqn-online"),
        }
    }
}

impl PolicySpec {
    /// The policy's name as `--policy` spells it, without the argument of `eps:P` and
    /// `actions:FILE`.
    pub fn name(&self) -> &'static str {
        match self {
            Self::Random => "random",
            Self::Stalest => "stalest",
            Self::Greedy => "greedy",
            Self::Planner => "planner",
            Self::DqnOnline => "dqn-online",
            Self::Epsilon(_) => "eps",
            Self::Actions(_) => "actions",
            Self::Checkpoint { .. } => "q",
        }
    }

    /// The policy, its random stream seeded by `seed`, for `config`'s world, asked for `steps`
    /// actions in all (a replayed list must hold that many; `None`: as many as it holds).
    pub fn build(
        &self,
        config: &Config,
        seed: u64,
        steps: Option<usize>,
    ) -> Result<Box<dyn Policy>, PolicyError> {
        let policy = self.build_any(config, seed, steps)?;
        self.for_world(config, policy)
    }

    /// `policy`, this spec's, if it can fly `config`'s world: a team's needs a team policy.
    pub fn for_world(
        &self,
        config: &Config,
        policy: Box<dyn Policy>,
    ) -> Result<Box<dyn Policy>, PolicyError> {
        let uavs = config.world.uavs;
        if uavs == 1 || policy.acts_for_teams() {
            return Ok(policy);
        }
        Err(PolicyError::Spec {
            spec: self.to_string(),
            expected: format!(
                "a policy that acts for a team of world.uavs = {uavs}: random, stalest, greedy, \
                 planner, eps:P or actions:FILE (learned policies fly one UAV so far, \
                 docs/MODEL.md section 11)"
            ),
        })
    }

    fn build_any(
        &self,
        config: &Config,
        seed: u64,
        steps: Option<usize>,
    ) -> Result<Box<dyn Policy>, PolicyError> {
        let action_count = config.world.layout().action_count();
        Ok(match self {
            Self::Random => Box::new(RandomPolicy::new(seed)),
            Self::Stalest => Box::new(StalestPolicy),
            Self::Greedy => Box::new(GreedyPolicy),
            Self::Epsilon(p) => Box::new(EpsilonPolicy::new(*p, seed)),
            Self::Planner => {
                let fits = config.planner.fits(&config.world);
                fits.map_err(|expected| PolicyError::Spec {
                    spec: self.to_string(),
                    expected: format!("{expected} (lower planner.beam_width)"),
                })?;
                Box::new(PlannerPolicy::new(&config.planner))
            }
            Self::Actions(path) => {
                let replay = ReplayPolicy::from_file(path, action_count)?;
                if let Some(need) = Some(steps.unwrap_or(1)).filter(|&need| replay.len() < need) {
                    return Err(PolicyError::TooShort { path: path.clone(), have: replay.len(), need });
                }
                Box::new(replay)
            }
            Self::DqnOnline => {
                return Err(PolicyError::Spec {
                    spec: self.to_string(),
                    expected: "a fixed policy; dqn-online must first be trained in the task's world (`uavmeta collect --policy dqn-online`)".into(),
                })
            }
            Self::Checkpoint { .. } => {
                return Err(PolicyError::Spec {
                    spec: self.to_string(),
                    expected: "a policy without a network; a checkpoint's policy is built by `uavmeta_actors::policy::build`".into(),
                })
            }
        })
    }
}

/// The reference rows of every results table and figure, in their order: uniform random, the two
/// heuristics and the planner reference, so a learned return reads between "random" and
/// "achievable".
pub const REFERENCES: [PolicySpec; 4] = [
    PolicySpec::Random,
    PolicySpec::Stalest,
    PolicySpec::Greedy,
    PolicySpec::Planner,
];

/// Each of [`REFERENCES`] on `task`, evaluated as learned policies are
/// ([`crate::rollout::evaluate`]: every start cell where the world is deterministic, else
/// `episodes` Monte-Carlo episodes), its randomness seeded by `learner.eval_seed`.
pub fn reference_metrics(
    config: &Config,
    task: &TaskConfig,
    episodes: usize,
) -> Vec<(PolicySpec, PolicyMetrics)> {
    let seed = config.learner.eval_seed;
    REFERENCES
        .into_iter()
        .map(|spec| {
            let mut policy = spec
                .build(config, seed, None)
                .expect("the references need no file");
            let metrics = evaluate(&config.world, task, policy.as_mut(), episodes, seed);
            (spec, metrics)
        })
        .collect()
}

/// The model-based section's reference on `task`: the planner run in the world `shots` identify
/// (`crate::identify`, told the world's form only), the plan made in the fitted world from each
/// state the true world shows and played there, evaluated as [`reference_metrics`] evaluates.
/// Why not, where the shots fit no world (rain, or steps of another world).
pub fn model_planner_metrics(
    config: &Config,
    task: &TaskConfig,
    shots: &[Transition],
    episodes: usize,
) -> Result<PolicyMetrics, Unidentified> {
    let fitted = identify(&config.world, shots)?;
    let mut policy = PlannerPolicy::in_model(&config.planner, fitted.world);
    let seed = config.learner.eval_seed;
    Ok(evaluate(&config.world, task, &mut policy, episodes, seed))
}

/// The device with the largest delta_k A_k not in `claimed`, ties to the lowest index; if every
/// device is claimed, the stalest of all.
fn stalest_device(world: &World, claimed: &Claims) -> usize {
    let all_claimed = claimed.all(world.devices());
    world
        .aoi()
        .iter()
        .zip(world.delta())
        .map(|(&a, &d)| d * a as f64)
        .enumerate()
        .filter(|&(k, _)| all_claimed || !claimed.has(k))
        .fold((0, f64::NEG_INFINITY), |best, (k, v)| {
            if v > best.1 {
                (k, v)
            } else {
                best
            }
        })
        .0
}

/// Where a UAV at `from` flies to serve `device`: the device's cell, or in a task with a risky
/// region the cell nearest it outside the region that whole moves from `from` reach exactly
/// (with moves of several cells not every cell is, and a UAV that stops short next to its goal
/// must not stop inside the region; ties to the lowest y, then x).
fn safe_cell(world: &World, from: (u32, u32), device: usize) -> (u32, u32) {
    let at = world.device_cells()[device];
    if world.risky_region().is_none() {
        return at;
    }
    let (grid, s) = (world.grid_cells(), world.step_cells());
    let reached = |(x, y): (u32, u32)| x.abs_diff(from.0) % s == 0 && y.abs_diff(from.1) % s == 0;
    let distance2 = |(x, y): (u32, u32)| x.abs_diff(at.0).pow(2) + y.abs_diff(at.1).pow(2);
    (0..grid)
        .flat_map(|y| (0..grid).map(move |x| (x, y)))
        .filter(|&c| reached(c) && world.expected_penalty_at(c, device) == 0.0)
        .min_by_key(|&c| distance2(c))
        .unwrap_or(at)
}

/// One step from `cell` towards `device`'s cell (see [`towards_cell`]).
fn towards(world: &World, cell: (u32, u32), device: usize) -> Move {
    towards_cell(world, cell, world.device_cells()[device])
}

/// One step from `(ux, uy)` towards `(dx, dy)`, x first; hover there. With moves of several
/// cells, an axis at least a move away comes first, then one a move brings nearer; hover when
/// no move brings the UAV nearer.
fn towards_cell(world: &World, (ux, uy): (u32, u32), (dx, dy): (u32, u32)) -> Move {
    use std::cmp::Ordering::{Greater, Less};
    let s = world.step_cells();
    let axes = [
        (ux.abs_diff(dx), ux.cmp(&dx), Move::East, Move::West),
        (uy.abs_diff(dy), uy.cmp(&dy), Move::North, Move::South),
    ];
    let far = axes.iter().find(|a| a.0 >= s);
    let near = || axes.iter().find(|a| 2 * a.0 > s);
    match far.or_else(near) {
        Some(&(_, Less, up, _)) => up,
        Some(&(_, Greater, _, down)) => down,
        _ => Move::Hover,
    }
}
