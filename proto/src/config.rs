//! Experiment configuration: SPEC section 7's TOML layout with every default of SPEC sections 1-5.
//!
//! A file names only what it changes; [`Config::load`] reads it, applies `--set KEY=VALUE`
//! overrides, and validates the result. Every error names the file (or the override), the key, the
//! offending value and what was expected.

use std::fmt;
use std::ops::Bound::Excluded;
use std::path::{Path, PathBuf};
use std::str::FromStr;

use garde::Validate;
use serde::{Deserialize, Serialize};

mod rules;

use rules::Broken;
use rules::{
    at_least, at_most, finite, first_broken, increasing, is_weight, list_of, non_empty, positive,
    satisfies, toml_seed, widths, within,
};

/// The largest number of devices a world may have: the zero-copy transition slot of
/// `proto::transport` stores observations in fixed-size arrays of `2 + MAX_DEVICES` entries.
pub const MAX_DEVICES: usize = 64;

/// SPEC section 1's moves by name, in action-index order: action `a = move * K + device`.
/// Exports and `uavmeta dataset inspect` name actions with them; `actors::world::Move` is the
/// world's own enum in the same order.
pub const MOVES: [&str; 5] = ["north", "south", "east", "west", "hover"];

/// The largest grid side: the world precomputes a power table of grid_cells^2 x K entries.
pub const MAX_GRID_CELLS: u32 = 1024;

/// A config error. `origin` is the file path, or `--set KEY=VALUE` for an override.
#[derive(Debug, thiserror::Error)]
pub enum ConfigError {
    #[error("{origin}: cannot read: {error}")]
    Read {
        origin: String,
        error: std::io::Error,
    },
    #[error("{origin}: {message}")]
    Parse { origin: String, message: String },
    #[error("{origin}: key `{key}` = {value}: expected {expected}")]
    Invalid {
        origin: String,
        key: String,
        value: String,
        expected: String,
    },
    #[error("{origin}: no task named `{name}`; the config defines: {known}")]
    UnknownTask {
        origin: String,
        name: String,
        known: String,
    },
}

/// One experiment: the world, its tasks, and the settings of every stage.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, Validate)]
#[serde(deny_unknown_fields)]
#[garde(allow_unvalidated)]
pub struct Config {
    #[serde(default)]
    #[garde(dive)]
    pub world: WorldConfig,
    #[serde(default = "default_tasks")]
    #[garde(custom(non_empty("at least one [[tasks]] table")), dive)]
    pub tasks: Vec<TaskConfig>,
    #[serde(default)]
    #[garde(dive)]
    pub collect: CollectConfig,
    #[serde(default)]
    #[garde(dive)]
    pub learner: LearnerConfig,
    #[serde(default)]
    #[garde(dive)]
    pub meta: MetaConfig,
    #[serde(default)]
    #[garde(dive)]
    pub run: RunConfig,
    #[serde(default)]
    #[garde(dive)]
    pub reproduce: ReproduceConfig,
    #[serde(default)]
    #[garde(dive)]
    pub tunnel: TunnelConfig,
    #[serde(default)]
    #[garde(dive)]
    pub planner: PlannerConfig,
    /// Where the config was read from; not part of the TOML.
    #[serde(skip)]
    pub origin: String,
}

/// SPEC section 1: the grid, the devices, the UAV, the channel and the rain model.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, Validate)]
#[serde(deny_unknown_fields, default)]
#[garde(allow_unvalidated)]
pub struct WorldConfig {
    /// Cells per side, L.
    #[garde(custom(within(
        1..=MAX_GRID_CELLS,
        format!("between 1 and {MAX_GRID_CELLS} cells per side")
    )))]
    pub grid_cells: u32,
    /// Side of a cell in metres, r.
    #[garde(custom(finite(0.0.., "a finite number >= 0")))]
    pub cell_m: f64,
    /// Number of IoT devices, K.
    #[garde(custom(at_least(1)), custom(at_most(MAX_DEVICES)))]
    pub devices: usize,
    /// Explicit device cells `[[x, y], ...]`; when absent, `layout_seed` draws distinct cells.
    pub device_cells: Option<Vec<[u32; 2]>>,
    /// Seed of the device layout when `device_cells` is absent.
    #[garde(custom(toml_seed()))]
    pub layout_seed: u64,
    /// Importance weight delta_k: one number for every device, or one per device.
    #[garde(custom(satisfies(Delta::is_weights, "finite weights >= 0")))]
    pub delta: Delta,
    /// UAV height h in metres.
    #[garde(custom(finite(0.0.., "a finite number >= 0")))]
    pub height_m: f64,
    /// Episode length T in steps; the end of an episode is a time limit, not a terminal state.
    #[garde(custom(within(1.., "at least 1 step")))]
    pub horizon: u32,
    /// AoI cap A_max.
    #[garde(custom(within(1..=u32::from(u16::MAX), "between 1 and 65535")))]
    pub aoi_max: u32,
    /// Fixed start cell of the UAV; uniform at random each episode when absent.
    pub start_cell: Option<[u32; 2]>,
    /// Channel gain at 1 m, g0, in dB.
    #[garde(custom(finite(.., "a finite number of dB")))]
    pub g0_db: f64,
    /// Bandwidth B in Hz.
    #[garde(custom(finite(0.0.., "a finite number >= 0")))]
    pub bandwidth_hz: f64,
    /// Bits per update M.
    #[garde(custom(finite(0.0.., "a finite number >= 0")))]
    pub bits: f64,
    /// Noise power sigma^2 in dBm.
    #[garde(custom(finite(.., "a finite number of dB")))]
    pub noise_dbm: f64,
    /// Which powers enter the reward: the scheduled device's only, or all K devices'.
    pub power_term: PowerTerm,
    /// Rain rate R in mm/h.
    #[garde(custom(finite(0.0.., "a finite number >= 0")))]
    pub rain_mm_per_h: f64,
    /// ITU-R P.838 coefficient phi (k).
    #[garde(custom(finite(0.0.., "a finite number >= 0")))]
    pub rain_phi: f64,
    /// ITU-R P.838 exponent varphi (alpha).
    #[garde(custom(finite(0.0.., "a finite number >= 0")))]
    pub rain_varphi: f64,
}

impl Default for WorldConfig {
    fn default() -> Self {
        Self {
            grid_cells: 10,
            cell_m: 100.0,
            devices: 10,
            device_cells: None,
            layout_seed: 0,
            delta: Delta::Uniform(1.0),
            height_m: 100.0,
            horizon: 100,
            aoi_max: 100,
            start_cell: None,
            g0_db: -30.0,
            bandwidth_hz: 1e6,
            bits: 5e6,
            noise_dbm: -100.0,
            power_term: PowerTerm::Scheduled,
            rain_mm_per_h: 12.5,
            rain_phi: 0.2051,
            rain_varphi: 0.9679,
        }
    }
}

impl WorldConfig {
    /// Length of an observation, 2 + K.
    pub fn observation_len(&self) -> usize {
        2 + self.devices
    }

    /// Number of discrete actions, 5 moves x K devices.
    pub fn action_count(&self) -> usize {
        MOVES.len() * self.devices
    }

    /// Divisors that normalise a raw observation for the networks: x/(L-1), y/(L-1), A/aoi_max.
    pub fn observation_scale(&self) -> Vec<f32> {
        let span = (self.grid_cells.max(2) - 1) as f32;
        let mut scale = vec![span, span];
        scale.resize(self.observation_len(), self.aoi_max as f32);
        scale
    }

    /// delta_k for every device.
    pub fn delta_per_device(&self) -> Vec<f64> {
        match &self.delta {
            Delta::Uniform(d) => vec![*d; self.devices],
            Delta::PerDevice(d) => d.clone(),
        }
    }

    /// Rain-specific attenuation gamma_R = phi * R^varphi in dB/km.
    pub fn rain_attenuation_db_per_km(&self) -> f64 {
        self.rain_phi * self.rain_mm_per_h.powf(self.rain_varphi)
    }

    /// Whether cell `c` is inside the grid.
    fn inside(&self, c: [u32; 2]) -> bool {
        c[0] < self.grid_cells && c[1] < self.grid_cells
    }

    /// The devices fit the grid, one to a cell and each with its weight; the start is inside.
    fn check_layout(&self) -> Result<(), Broken> {
        let cells = self.grid_cells as usize * self.grid_cells as usize;
        if self.devices > cells {
            let expected = format!("between 1 and the number of cells, grid_cells^2 = {cells}");
            return Err(Broken::new("world.devices", &self.devices, expected));
        }
        if let Some(device_cells) = &self.device_cells {
            self.check_device_cells(device_cells)?;
        }
        if let Delta::PerDevice(d) = &self.delta {
            if d.len() != self.devices {
                let expected = format!("one weight or {} weights", self.devices);
                return Err(Broken::new("world.delta", d, expected));
            }
        }
        match self.start_cell {
            Some(c) if !self.inside(c) => Err(Broken::new(
                "world.start_cell",
                &c,
                "a cell inside the grid",
            )),
            _ => Ok(()),
        }
    }

    /// One distinct cell inside the grid per device.
    fn check_device_cells(&self, cells: &[[u32; 2]]) -> Result<(), Broken> {
        if cells.len() != self.devices {
            let expected = format!(
                "one cell per device: {} cells (world.devices)",
                self.devices
            );
            return Err(Broken::new("world.device_cells", &cells, expected));
        }
        for (i, c) in cells.iter().enumerate() {
            let key = format!("world.device_cells[{i}]");
            if !self.inside(*c) {
                let expected = format!(
                    "a cell inside the grid, each index below grid_cells = {}",
                    self.grid_cells
                );
                return Err(Broken::new(key, c, expected));
            }
            if cells[..i].contains(c) {
                return Err(Broken::new(key, c, "a cell no other device occupies"));
            }
        }
        Ok(())
    }
}

/// delta: a number for every device, or a list with one per device.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(untagged)]
pub enum Delta {
    Uniform(f64),
    PerDevice(Vec<f64>),
}

impl Delta {
    /// The weights as written: one, or one per device.
    pub fn weights(&self) -> &[f64] {
        match self {
            Delta::Uniform(d) => std::slice::from_ref(d),
            Delta::PerDevice(d) => d,
        }
    }

    /// Whether every weight is finite and at least 0.
    fn is_weights(&self) -> bool {
        self.weights().iter().all(is_weight)
    }
}

/// Which transmit powers the reward charges.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum PowerTerm {
    /// Only the scheduled device transmits, so the sum over devices is its one power.
    Scheduled,
    /// The literal reading: the sum over all K devices of the power each would need.
    AllDevices,
}

/// A rectangle of cells, both corners inclusive.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RainZone {
    pub x0: u32,
    pub y0: u32,
    pub x1: u32,
    pub y1: u32,
}

impl RainZone {
    pub fn contains(&self, x: u32, y: u32) -> bool {
        (self.x0..=self.x1).contains(&x) && (self.y0..=self.y1).contains(&y)
    }
}

impl FromStr for RainZone {
    type Err = String;

    /// Parses `x0,y0,x1,y1`, the form of the `--rain` flag.
    fn from_str(s: &str) -> Result<Self, String> {
        let parts: Vec<u32> = s
            .split(',')
            .map(|p| p.trim().parse::<u32>())
            .collect::<Result<_, _>>()
            .map_err(|_| format!("`{s}`: expected four cell indices x0,y0,x1,y1"))?;
        match parts[..] {
            [x0, y0, x1, y1] => Ok(Self { x0, y0, x1, y1 }),
            _ => Err(format!("`{s}`: expected four cell indices x0,y0,x1,y1")),
        }
    }
}

/// Whether a task is used for meta-training or held out for meta-testing.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum TaskRole {
    MetaTrain,
    MetaTest,
}

/// SPEC sections 2-3: one task is the world with its lambda and optional rain.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, Validate)]
#[serde(deny_unknown_fields)]
#[garde(allow_unvalidated)]
pub struct TaskConfig {
    pub name: String,
    /// The AoI-power trade-off.
    #[garde(custom(finite(0.0.., "a finite number >= 0")))]
    pub lambda: f64,
    pub role: TaskRole,
    #[serde(default)]
    pub rain: Option<RainZone>,
    /// Relocate the rain zone uniformly at random every this many steps.
    #[serde(default)]
    #[garde(inner(custom(within(1.., "at least 1 step"))))]
    pub rain_moves_every: Option<u32>,
}

impl TaskConfig {
    /// As [`TaskConfig::one_off`], its rain zone moving every `every` steps
    /// (`--rain-moves-every N`); the name says so.
    pub fn one_off_moving(lambda: f64, rain: RainZone, every: u32) -> Self {
        let task = Self::one_off(lambda, Some(rain));
        Self {
            name: format!("{}-moves-{every}", task.name),
            rain_moves_every: Some(every),
            ..task
        }
    }

    /// A task given on the command line (`--lambda X [--rain x0,y0,x1,y1]`) instead of by name.
    pub fn one_off(lambda: f64, rain: Option<RainZone>) -> Self {
        let name = match rain {
            None => format!("lambda-{lambda}"),
            Some(r) => format!("lambda-{lambda}-rain-{}-{}-{}-{}", r.x0, r.y0, r.x1, r.y1),
        };
        Self {
            name,
            lambda,
            role: TaskRole::MetaTest,
            rain,
            rain_moves_every: None,
        }
    }
}

/// The paper's setting (SPEC section 2): meta-train on eight lambdas, meta-test on lambda = 300.
fn default_tasks() -> Vec<TaskConfig> {
    let mut tasks: Vec<TaskConfig> = [0.0, 100.0, 200.0, 400.0, 500.0, 600.0, 800.0, 1000.0]
        .into_iter()
        .map(|lambda| TaskConfig {
            name: format!("lambda-{lambda}"),
            lambda,
            role: TaskRole::MetaTrain,
            rain: None,
            rain_moves_every: None,
        })
        .collect();
    tasks.push(TaskConfig::one_off(300.0, None));
    tasks
}

/// SPEC section 4: how each task's dataset is collected, and the online DQN behaviour policy.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, Validate)]
#[serde(deny_unknown_fields, default)]
#[garde(allow_unvalidated)]
pub struct CollectConfig {
    /// Behaviour policy: `dqn-online`, `random`, `stalest`, `greedy` or `eps:P` (stalest with
    /// probability 1-P, uniform random with probability P).
    pub policy: String,
    /// Transitions kept per task (the paper's datasets hold 500).
    #[garde(custom(at_least(1)))]
    pub transitions: usize,
    /// Actor processes per task in a launched run.
    #[garde(custom(at_least(1)))]
    pub actors_per_task: usize,
    /// Base seed of the behaviour policies and their worlds.
    #[garde(custom(toml_seed()))]
    pub seed: u64,
    /// Environment steps the online DQN agent trains for before its replay buffer is sampled.
    pub dqn_steps: usize,
    /// Replay buffer capacity of the online DQN agent.
    #[garde(custom(at_least(1)))]
    pub replay_capacity: usize,
    /// Steps of uniform random actions before the first gradient step.
    pub learning_starts: usize,
    /// Environment steps between gradient steps.
    #[garde(custom(at_least(1)))]
    pub train_every: usize,
    /// Epsilon-greedy schedule: linear from `eps_start` to `eps_end` over `eps_decay_steps`.
    /// `eps_end` 0.01 (Rainbow's and Dopamine's value): at 0.05 the agents of the AoI-dominated
    /// tasks (lambda 0 and 100) ended up to 7% below the heuristics on their worst seed, at 0.01
    /// within 1.7% (docs/EXPERIMENTS.md, section A).
    #[garde(custom(within(0.0..=1.0, "a probability in [0, 1]")))]
    pub eps_start: f64,
    #[garde(custom(within(0.0..=1.0, "a probability in [0, 1]")))]
    pub eps_end: f64,
    pub eps_decay_steps: usize,
    /// Hidden layer widths of the online agent's Q-network (SPEC section 5's [256, 256]; the
    /// offline learners' network is `learner.hidden`).
    #[garde(custom(widths()))]
    pub dqn_hidden: Vec<usize>,
    /// Adam learning rate of the online agent. Lower than offline training's: the agent takes
    /// tens of thousands of steps on a buffer that keeps changing, and at 1e-3 its greedy policy
    /// swings by a fifth of its return from one evaluation to the next.
    #[garde(custom(positive("a finite rate > 0")))]
    pub dqn_lr: f64,
    /// Double DQN targets for the online agent (van Hasselt et al.): the online network picks
    /// the next action, the target network values it.
    pub dqn_double: bool,
    /// Huber (delta = 1) instead of the squared TD error for the online agent.
    pub dqn_huber: bool,
    /// Clip the online agent's gradient to this global L2 norm; 0 = no clipping.
    #[garde(custom(finite(0.0.., "a finite norm >= 0 (0 = no clipping)")))]
    pub dqn_grad_clip_norm: f64,
    /// Gradient steps between the online agent's hard target-network updates. Slower than the
    /// usual 500: at lambda = 0 the best and second-best actions differ by a fraction of a percent
    /// of Q, and a target refreshed every 500 steps moves more than that (docs/EXPERIMENTS.md, A2).
    #[garde(custom(at_least(1)))]
    pub dqn_target_update_every: usize,
    /// Steps in the online agent's bootstrapped return: the target of a transition is
    /// `sum_{k<n} gamma^k r_{t+k} + gamma^n V(s_{t+n})`, cut short at the episode's end (the
    /// horizon, which still bootstraps) and at the newest transition of the buffer. 1 is eq. 7.
    /// The dataset stays one-step transitions whatever this is.
    pub dqn_n_step: usize,
    /// The online agent's learning rate falls linearly from `dqn_lr` at `learning_starts` to
    /// `dqn_lr * dqn_lr_final_fraction` at `dqn_steps`; 1 keeps it constant.
    #[garde(custom(within(0.0..=1.0, "a fraction in [0, 1] (1 = a constant rate)")))]
    pub dqn_lr_final_fraction: f64,
    /// Environment steps between exact evaluations of the online agent's greedy policy (over
    /// every start cell; `learner.eval_episodes` Monte-Carlo episodes of its own seed where the
    /// rain moves), from the step epsilon reaches `eps_end` to `dqn_steps`, the last step always
    /// among them. The agent's policy, saved as the task's online reference, is the best of those
    /// snapshots rather than the last, as an online learner with a simulator may choose
    /// (Stable-Baselines3's EvalCallback): the last iterate's return moves by 1-3% between
    /// neighbouring evaluations (docs/EXPERIMENTS.md, A5). Training, and so the replay buffer and
    /// the dataset sampled from it, is the same whatever this is. 0 = keep the last policy.
    pub dqn_select_every: usize,
    /// The dataset is sampled from the newest this many transitions of the agent's final replay
    /// buffer; 0 = the whole buffer (the paper's "sampled from the replay buffer").
    pub sample_newest: usize,
    /// Where a command trains several online agents (`uavmeta reproduce`'s datasets), up to this
    /// many train as one population: stacked networks stepped and updated as one computation
    /// (`actors::policy::dqn_population`). A population of one is the single agent bit for bit;
    /// larger ones give each member its separate run up to float rounding. 1 (one at a time) is
    /// the fastest on CPU, where a [256, 256] step already runs at 60-70% of its matrix
    /// products' floor; stacking is for accelerators (docs/BENCHMARKS.md, "Populations").
    #[garde(custom(at_least(1)))]
    pub population: usize,
}

impl CollectConfig {
    /// How many of the online agent's last steps its dataset is sampled from: the final replay
    /// buffer (`min(dqn_steps, replay_capacity)`), cut to its newest `sample_newest` when set.
    pub fn sampled_window(&self) -> usize {
        let held = self.dqn_steps.min(self.replay_capacity);
        match self.sample_newest {
            0 => held,
            n => held.min(n),
        }
    }
}

impl Default for CollectConfig {
    fn default() -> Self {
        Self {
            policy: "dqn-online".into(),
            transitions: 500,
            actors_per_task: 1,
            seed: 0,
            dqn_steps: 30_000,
            replay_capacity: 10_000,
            learning_starts: 1_000,
            train_every: 1,
            eps_start: 1.0,
            eps_end: 0.01,
            eps_decay_steps: 12_000,
            dqn_hidden: vec![256, 256],
            dqn_lr: 1e-4,
            dqn_double: true,
            dqn_huber: true,
            dqn_grad_clip_norm: 10.0,
            dqn_target_update_every: 2_000,
            dqn_n_step: 1,
            dqn_lr_final_fraction: 1.0,
            dqn_select_every: 0,
            sample_newest: 0,
            population: 1,
        }
    }
}

/// SPEC section 5: the Q-network and the DQN / CQL training settings shared by every method.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, Validate)]
#[serde(deny_unknown_fields, default)]
#[garde(allow_unvalidated)]
pub struct LearnerConfig {
    /// Hidden layer widths of the Q-network MLP.
    #[garde(custom(widths()))]
    pub hidden: Vec<usize>,
    /// Discount factor gamma.
    #[garde(custom(within(0.0..=1.0, "a discount in [0, 1]")))]
    pub gamma: f64,
    /// Rewards are multiplied by this before any loss sees them. A step costs around 100 (the
    /// AoI sum alone is K times the mean AoI), so unscaled Q-values reach -10^4 and Adam at
    /// lr = 1e-3 needs tens of thousands of steps just to move the output that far; 0.01 is the
    /// paper's own plotting scale (reward / 100). Reported Q-values are divided back.
    #[garde(custom(positive("a finite number > 0")))]
    pub reward_scale: f64,
    /// CQL conservative weight alpha (eq. 8).
    #[garde(custom(finite(0.0.., "a finite number >= 0")))]
    pub alpha: f64,
    /// Minibatch size.
    #[garde(custom(at_least(1)))]
    pub batch: usize,
    /// Adam learning rate of offline training and fine-tuning (eta_outer, so every method
    /// shares the meta-learner's optimiser settings).
    #[garde(custom(positive("a learning rate > 0")))]
    pub lr: f64,
    /// Training epochs E.
    pub epochs: usize,
    /// Gradient steps per epoch; 0 means one pass over the dataset, ceil(N / batch).
    pub steps_per_epoch: usize,
    /// Gradient steps between hard target-network updates.
    #[garde(custom(at_least(1)))]
    pub target_update_every: usize,
    /// Double DQN targets (d3rlpy's choice); off to match eq. 7.
    pub double_dqn: bool,
    /// Huber instead of squared TD error (d3rlpy's choice); off to match eq. 7.
    pub huber: bool,
    /// Guard against late collapse, from the offline data alone: training stops, keeping the
    /// previous epoch's network, once the mean Q of the data's own actions falls below
    /// `V_data - value_guard * |V_data|`, `V_data` = the shots' mean reward / (1 - gamma) (see
    /// `learner/src/train.rs`). 0 = no guard.
    #[garde(custom(finite(0.0.., "a finite margin >= 0 (0 = no guard)")))]
    pub value_guard: f64,
    /// Monte-Carlo episodes of each evaluation of a greedy policy.
    pub eval_episodes: usize,
    /// Seed of the evaluation episodes, the same for every method and epoch.
    #[garde(custom(toml_seed()))]
    pub eval_seed: u64,
}

impl Default for LearnerConfig {
    fn default() -> Self {
        Self {
            hidden: vec![256, 256],
            gamma: 0.99,
            reward_scale: 0.01,
            alpha: 1.0,
            batch: 64,
            lr: 1e-3,
            epochs: 100,
            steps_per_epoch: 0,
            target_update_every: 100,
            double_dqn: false,
            huber: false,
            value_guard: 0.5,
            eval_episodes: 20,
            eval_seed: 12345,
        }
    }
}

/// A Q-learning loss: MAML's inner loss (`meta.inner_loss`), offline training's (`uavmeta train
/// --algo`) and each fine-tuned method's.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Loss {
    /// Paper eq. 8.
    Cql,
    /// Paper eq. 7 on a fixed dataset: the baseline that overestimates.
    Dqn,
}

impl fmt::Display for Loss {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            Loss::Cql => "cql",
            Loss::Dqn => "dqn",
        })
    }
}

impl std::str::FromStr for Loss {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "cql" => Ok(Loss::Cql),
            "dqn" => Ok(Loss::Dqn),
            _ => Err(format!("`{s}`: expected `cql` or `dqn`")),
        }
    }
}

/// SPEC section 5: MAML over CQL (Algorithm 4).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, Validate)]
#[serde(deny_unknown_fields, default)]
#[garde(allow_unvalidated)]
pub struct MetaConfig {
    /// Meta-epochs E_meta.
    pub meta_epochs: usize,
    /// Outer (eq. 16) steps per meta-epoch; 0 = one pass over the tasks' support sets, i.e.
    /// ceil(support shots / `shots`) steps, each task's support shots drawn without replacement
    /// within the pass (SPEC section 5, "Epochs"). 1 = Algorithm 4 read literally.
    pub outer_steps_per_meta_epoch: usize,
    /// Tasks sampled per meta-epoch; 0 means every meta-train task.
    pub tasks_per_meta_epoch: usize,
    /// k: transitions drawn from a task's support set each meta-epoch; every inner step uses the
    /// same k, as in MAML.
    #[garde(custom(at_least(1)))]
    pub shots: usize,
    /// Transitions of a task's query set per meta-loss evaluation.
    #[garde(custom(at_least(1)))]
    pub query_shots: usize,
    /// Share of each task's dataset that forms its support set; the rest is its query set.
    #[garde(custom(within((Excluded(0.0), Excluded(1.0)), "a share strictly between 0 and 1")))]
    pub support_fraction: f64,
    /// SGD steps of the inner loop.
    #[garde(custom(at_least(1)))]
    pub inner_steps: usize,
    #[garde(custom(positive("a learning rate > 0")))]
    pub eta_inner: f64,
    #[garde(custom(positive("a learning rate > 0")))]
    pub eta_outer: f64,
    /// Eq. 16's step size falls linearly over the meta-epochs, from `eta_outer` in the first to
    /// `eta_outer * eta_outer_final_fraction` in the last; 1 keeps it constant.
    #[garde(custom(within(0.0..=1.0, "a fraction in [0, 1] (1 = a constant step size)")))]
    pub eta_outer_final_fraction: f64,
    /// First-order MAML: do not differentiate through the inner steps.
    pub first_order: bool,
    /// Meta-SGD (Li et al., 2017): learn eq. 14's step size, one per weight, initialised to
    /// `eta_inner` and updated by eq. 16's Adam together with w0; false is MAML's one fixed
    /// `eta_inner`.
    pub learn_inner_lr: bool,
    /// CQL-MAML (the paper's method) or DQN-MAML (its baseline).
    pub inner_loss: Loss,
    /// Eq. 8's conservative weight alpha in MAML's losses (eqs. 14-15) and in CQL-pretrain's
    /// multi-task training, the two inits; `learner.alpha` is the weight of the offline training
    /// and fine-tuning on a task's shots. SPEC's alpha = 1 for both.
    #[garde(custom(finite(0.0.., "a finite number >= 0")))]
    pub alpha: f64,
    /// Huber instead of squared TD error in MAML's losses (eqs. 14-15) even when fine-tuning keeps
    /// the square; `learner.huber` turns it on for both. Off to match eq. 7.
    pub huber: bool,
    /// Meta-epochs between w0 checkpoints.
    #[garde(custom(within(1.., "at least 1 meta-epoch")))]
    pub checkpoint_every: usize,
    /// Meta-epochs between refreshes of the target network Qhat from w0; Qhat is held constant
    /// through the inner and outer losses in between (see `meta/src/maml.rs`).
    #[garde(custom(within(1.., "at least 1 meta-epoch")))]
    pub target_update_every: usize,
    /// Meta-epochs between evaluations of each task's adapted greedy policy on its environment
    /// (costly: `learner.eval_episodes` episodes per task); 0 evaluates only after the last.
    pub eval_every: usize,
    /// Polyak averaging of the meta-iterates: after every outer step the published init becomes
    /// `decay * init + (1 - decay) * w0`, an exponential moving average of w0 over the last
    /// 1 / (1 - decay) outer steps; checkpoints, evaluations and the meta-test use it, while eq.
    /// 16 keeps updating w0 itself. 0 = off: the init is the last iterate, whose return swung by
    /// up to 2.4k between neighbouring meta-epochs (docs/EXPERIMENTS.md, C7).
    #[garde(custom(within(0.0..1.0, "a decay in [0, 1): 0 = no averaging")))]
    pub w0_average_decay: f64,
    /// Independent adaptations (each on fresh `shots` support shots) per task and evaluation;
    /// the reported return is their mean, so that a figure-4 point measures the adapted return
    /// rather than sampling one adaptation of it.
    #[garde(custom(within(1.., "at least 1 adaptation per evaluation")))]
    pub eval_adaptations: usize,
}

impl Default for MetaConfig {
    fn default() -> Self {
        Self {
            meta_epochs: 150,
            outer_steps_per_meta_epoch: 0,
            tasks_per_meta_epoch: 0,
            shots: 64,
            query_shots: 64,
            support_fraction: 0.5,
            inner_steps: 1,
            eta_inner: 1e-2,
            eta_outer: 1e-3,
            eta_outer_final_fraction: 1.0,
            first_order: false,
            learn_inner_lr: false,
            inner_loss: Loss::Cql,
            alpha: 1.0,
            huber: false,
            checkpoint_every: 10,
            target_update_every: 1,
            eval_every: 10,
            w0_average_decay: 0.0,
            eval_adaptations: 1,
        }
    }
}

/// Where a run writes, its seeds, its metrics endpoints and its iceoryx2 capacities.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, Validate)]
#[serde(deny_unknown_fields, default)]
#[garde(allow_unvalidated)]
pub struct RunConfig {
    /// Run directory: datasets, checkpoints, CSV files, port files.
    pub dir: PathBuf,
    /// Seeds of repeated runs; the first is the seed of a single run.
    #[garde(custom(non_empty("at least one seed")), inner(custom(toml_seed())))]
    pub seeds: Vec<u64>,
    /// Address every /metrics endpoint binds.
    pub metrics_host: String,
    /// Port of the launcher's /metrics; children get 0 (an ephemeral port written to the run dir).
    pub metrics_port: u16,
    /// Transitions per zero-copy batch.
    #[garde(custom(at_least(1)), custom(at_most(MAX_BATCH_SIZE)))]
    pub batch_size: usize,
    /// Batches a subscriber buffers before publishers wait.
    #[garde(custom(at_least(1)), custom(at_most(MAX_SUBSCRIBER_BUFFER)))]
    pub subscriber_buffer: usize,
    /// Publishers (actors) a transition service admits.
    #[garde(custom(at_least(1)))]
    pub max_publishers: usize,
    /// A rollout actor keeps a copy of every batch until the store acknowledges it appended, and
    /// sends what is unacknowledged again to a store that replaced a killed one, so a store crash
    /// loses nothing. `false` keeps a copy only until the store is proven connected: cheaper for
    /// the actor (docs/BENCHMARKS.md, Transport), but a killed store's unwritten batches are then
    /// lost (counted as missing). A replay sample (`dqn-online`) is always sent again from the
    /// acknowledged number, since it needs no copy.
    pub keep_until_stored: bool,
    /// Restarts of a crashed or hung child before the launcher gives up.
    pub max_restarts: u32,
    /// A launched child whose heartbeat (`transport::heartbeat`) has not moved for this many
    /// seconds is taken for hung (stopped, deadlocked, livelocked), killed and restarted like a
    /// crashed one; 0 = never. Every process beats at least every few seconds on this machine
    /// under load, so the default leaves a wide margin.
    #[garde(custom(finite(0.0.., "seconds >= 0 (0 = never)")))]
    pub hang_timeout_seconds: f64,
    /// Announcements (dataset ready, checkpoint ready, shutdown) a control subscriber buffers;
    /// also the history a process joining late receives.
    #[garde(custom(at_least(1)), custom(at_most(MAX_SUBSCRIBER_BUFFER)))]
    pub control_buffer: usize,
    /// The iceoryx2 domain of this host's processes of the run: their shared memory is named
    /// `iox2_<domain>_...` and iceoryx2's files live in `/tmp/iceoryx2/<domain>/`, so processes of
    /// two domains cannot see each other even on one machine; empty = iceoryx2's default domain.
    /// Only a tunnel (`uavmeta tunnel`) connects domains. A remote host's copy of the config
    /// names its own (`uavmeta tunnel join --domain`).
    #[garde(custom(satisfies(
        is_domain,
        format!("at most {MAX_DOMAIN_LEN} letters, digits, '-' or '_' (empty = default)")
    )))]
    pub domain: String,
    /// The libtorch device populations of learners are made on: `cpu`, `cuda` or `cuda:N`.
    /// Asking for CUDA where libtorch sees no GPU is an error when the population is made. The
    /// CUDA path is device placement only and untested here (no GPU on the project's machines).
    #[garde(custom(satisfies(is_torch_device, "cpu, cuda or cuda:N")))]
    pub device: String,
}

/// Remote actor hosts reach the run through iceoryx2's tunnel over Zenoh (`uavmeta tunnel`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, Validate)]
#[serde(deny_unknown_fields, default)]
#[garde(allow_unvalidated)]
pub struct TunnelConfig {
    /// Zenoh endpoint where the launcher's tunnel accepts remote actor hosts, such as
    /// `tcp/0.0.0.0:7447`; empty = no tunnel, local actors only.
    #[garde(custom(satisfies(
        is_endpoint,
        "a Zenoh endpoint PROTOCOL/ADDRESS such as tcp/0.0.0.0:7447, or empty"
    )))]
    pub listen: String,
    /// Remote hosts (`uavmeta tunnel join --host`) whose actors the launcher waits for before it
    /// starts the local ones: until each has joined and the store has stored a transition, so
    /// that a run's data comes from every host it was planned with.
    pub wait_for_hosts: Vec<String>,
    /// How long the launcher waits for `wait_for_hosts` before it gives up.
    #[garde(custom(positive("seconds > 0")))]
    pub wait_seconds: f64,
    /// The run's CA certificate (PEM). With a `tls/` endpoint, which any address beyond loopback
    /// needs, a remote host is admitted only with a certificate this CA signed (mutual TLS).
    /// `uavmeta tunnel certs` makes the CA and every host's certificate.
    pub ca: PathBuf,
    /// This host's certificate (PEM), signed by `ca`, naming the address remote hosts connect to.
    pub certificate: PathBuf,
    /// The private key (PEM) of `certificate`; readable by this user only.
    pub private_key: PathBuf,
    /// A file of `user:password` lines (Zenoh's user-password dictionary): a remote host must also
    /// present one of them (`uavmeta tunnel join --credentials FILE`). Empty: certificates only.
    pub credentials: PathBuf,
}

impl Default for TunnelConfig {
    fn default() -> Self {
        Self {
            listen: String::new(),
            wait_for_hosts: Vec::new(),
            wait_seconds: 120.0,
            ca: PathBuf::new(),
            certificate: PathBuf::new(),
            private_key: PathBuf::new(),
            credentials: PathBuf::new(),
        }
    }
}

/// The planner reference (SPEC section 5, `uavmeta_world::planner`): a beam search over the
/// horizon that knows the world, the row every method's gap to "achievable" is read against.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, Validate)]
#[serde(deny_unknown_fields, default)]
#[garde(allow_unvalidated)]
pub struct PlannerConfig {
    /// States kept per step of the search. Exact (dynamic programming) once it holds every
    /// distinct state; on the default world 4x wider (1024) gains under 0.2% at 4x the time
    /// (docs/EXPERIMENTS.md, P).
    #[garde(custom(within(1.., "at least 1 state kept per step")))]
    pub beam_width: usize,
    /// The weights b of the power part of the search's cost-to-go estimate h
    /// (`uavmeta_world::planner`): the search runs once per weight and the cheapest plan is kept.
    /// The weight that ranks best moves with lambda (0.5 on lambda-300, 0.125 on lambda-1000 and
    /// lambda-2000), and the four together beat each alone on every lambda measured (each alone
    /// loses up to 4.2%, at lambda-2000), at four times the cost (docs/EXPERIMENTS.md, P2). 0
    /// ranks states by their cost so far and AoI alone.
    #[garde(custom(list_of(is_weight, "a non-empty list of finite weights >= 0")))]
    pub h_power_weights: Vec<f64>,
    /// The most memory one search may take, in MiB; a width and horizon that need more are
    /// refused up front.
    pub max_memory_mib: u64,
}

impl Default for PlannerConfig {
    fn default() -> Self {
        Self {
            beam_width: 256,
            h_power_weights: vec![0.5, 0.25, 0.125, 0.0625],
            max_memory_mib: 1024,
        }
    }
}

impl PlannerConfig {
    /// Bytes one search holds at its peak: width x T back-pointers, the beam, and one step's
    /// width x 5K children with their width x K aged AoI vectors of K entries.
    pub fn memory_bytes(&self, world: &WorldConfig) -> u128 {
        let (w, t, k) = (
            self.beam_width as u128,
            world.horizon as u128,
            world.devices as u128,
        );
        w * (t * 8 + (2 * k + 24) + 5 * k * 64 + k * k * 2)
    }
}

/// Longest `run.domain`: the iceoryx2 prefix of every shared-memory name grows with it.
pub const MAX_DOMAIN_LEN: usize = 32;

/// A `run.domain`: at most [`MAX_DOMAIN_LEN`] letters, digits, '-' or '_'.
fn is_domain(domain: &str) -> bool {
    domain.len() <= MAX_DOMAIN_LEN
        && domain
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || c == '_' || c == '-')
}

/// A libtorch device: `cpu`, `cuda` or `cuda:N`.
fn is_torch_device(device: &str) -> bool {
    let index = device.strip_prefix("cuda:").map(str::parse::<usize>);
    device == "cpu" || device == "cuda" || matches!(index, Some(Ok(_)))
}

/// A Zenoh endpoint `PROTOCOL/ADDRESS`, or empty (no tunnel).
fn is_endpoint(listen: &str) -> bool {
    listen.is_empty()
        || listen
            .split_once('/')
            .is_some_and(|(p, a)| !p.is_empty() && !a.is_empty())
}

impl Default for RunConfig {
    fn default() -> Self {
        Self {
            dir: PathBuf::from("runs/default"),
            seeds: vec![0],
            metrics_host: "127.0.0.1".into(),
            metrics_port: 0,
            batch_size: 64,
            subscriber_buffer: 64,
            max_publishers: 64,
            keep_until_stored: true,
            max_restarts: 5,
            hang_timeout_seconds: 60.0,
            control_buffer: 256,
            domain: String::new(),
            device: "cpu".into(),
        }
    }
}

/// `uavmeta reproduce`: the sizes of the paper's section V experiments (SPEC section 6). Keys that
/// name tasks or counts of tasks are checked against `[[tasks]]` by
/// [`Config::validate_reproduce`], when a reproduction starts, so that other commands accept a
/// config whose tasks do not fit them.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, Validate)]
#[serde(deny_unknown_fields, default)]
#[garde(allow_unvalidated)]
pub struct ReproduceConfig {
    /// Seeds 0..seeds-1 behind every curve; seed s collects its own datasets with
    /// `collect.seed + s`, so the spread covers the data as well as the learning.
    pub seeds: usize,
    /// The main experiments meta-train on the first this many meta-train tasks, in config order.
    #[garde(custom(at_least(1)))]
    pub meta_tasks: usize,
    /// Figure 7: meta-train on the first n meta-train tasks for each n.
    #[garde(custom(increasing("a non-empty, strictly increasing list of task counts >= 1")))]
    pub task_counts: Vec<usize>,
    /// Figure 6: the shot counts CQL and CQL-MAML are fine-tuned on.
    #[garde(custom(increasing("a non-empty, strictly increasing list of shot counts >= 1")))]
    pub shots: Vec<usize>,
    /// Shots of every other experiment (the paper's 500).
    #[garde(custom(at_least(1)))]
    pub main_shots: usize,
    /// The unseen task of figures 5-8 (role `meta-test`).
    #[garde(custom(non_empty("a task name")))]
    pub unseen_task: String,
    /// Figures 5 and 6: fine-tuning epochs.
    #[garde(custom(at_least(1)))]
    pub convergence_epochs: usize,
    /// Figure 7: fine-tuning epochs after which the task counts are compared.
    #[garde(custom(at_least(1)))]
    pub tasks_epochs: usize,
    /// Figure 8: the epoch whose AoI and power are compared.
    #[garde(custom(at_least(1)))]
    pub aoi_power_epoch: usize,
    /// Figure 9: fine-tuning epochs on each rain task (meta-test tasks with a rain zone).
    #[garde(custom(at_least(1)))]
    pub resilience_epochs: usize,
    /// Figure 9: Monte-Carlo episodes of each evaluation on a rain task.
    #[garde(custom(at_least(1)))]
    pub resilience_eval_episodes: usize,
    /// Figure 4: meta-epochs between evaluations of the adapted policies; 0 evaluates only after
    /// the last.
    pub meta_eval_every: usize,
}

impl Default for ReproduceConfig {
    fn default() -> Self {
        Self {
            seeds: 5,
            meta_tasks: 8,
            task_counts: vec![2, 4, 6, 8, 10],
            shots: vec![100, 300, 500],
            main_shots: 500,
            unseen_task: "lambda-300".into(),
            convergence_epochs: 100,
            tasks_epochs: 40,
            aoi_power_epoch: 50,
            resilience_epochs: 200,
            resilience_eval_episodes: 40,
            meta_eval_every: 10,
        }
    }
}

impl Default for Config {
    fn default() -> Self {
        Self {
            world: WorldConfig::default(),
            tasks: default_tasks(),
            collect: CollectConfig::default(),
            learner: LearnerConfig::default(),
            meta: MetaConfig::default(),
            run: RunConfig::default(),
            reproduce: ReproduceConfig::default(),
            tunnel: TunnelConfig::default(),
            planner: PlannerConfig::default(),
            origin: "<defaults>".into(),
        }
    }
}

impl Config {
    /// Reads `path`, applies `overrides` (`KEY=VALUE`, dotted keys as in the file, TOML values;
    /// a value that is not TOML is taken as a string) and validates the result.
    pub fn load(path: &Path, overrides: &[String]) -> Result<Self, ConfigError> {
        let source = path.display().to_string();
        let text = std::fs::read_to_string(path).map_err(|error| ConfigError::Read {
            origin: source.clone(),
            error,
        })?;
        Self::from_toml_str(&text, &source, overrides)
    }

    /// As [`Config::load`], from text already read; `source` names it in errors.
    pub fn from_toml_str(
        text: &str,
        source: &str,
        overrides: &[String],
    ) -> Result<Self, ConfigError> {
        let mut doc = text
            .parse::<toml_edit::DocumentMut>()
            .map_err(|e| ConfigError::Parse {
                origin: source.to_string(),
                message: e.to_string(),
            })?;
        if !doc.contains_key("tasks")
            && overrides
                .iter()
                .any(|o| o.trim_start().starts_with("tasks."))
        {
            // The file keeps the default tasks, which are not in the document: write them in so
            // that `tasks.N.KEY` has a table to index.
            let defaults: toml_edit::DocumentMut = Config::default()
                .to_toml_string()
                .parse()
                .expect("the default config is valid TOML");
            doc.insert("tasks", defaults["tasks"].clone());
        }
        for assignment in overrides {
            apply_override(&mut doc, source, assignment)?;
        }
        let source_desc = if overrides.is_empty() {
            source.to_string()
        } else {
            format!("{source} (with --set {})", overrides.join(" --set "))
        };
        let mut config: Config = toml::from_str(&doc.to_string()).map_err(|e| {
            let mut message = e.to_string().trim_end().to_string();
            if !overrides.is_empty() {
                // The parser saw the file with the overrides merged in, not the file itself.
                message
                    .push_str("\n(line numbers count the file with the --set overrides applied)");
            }
            ConfigError::Parse {
                origin: source_desc.clone(),
                message,
            }
        })?;
        config.origin = source_desc;
        config.validate()?;
        Ok(config)
    }

    /// The config as TOML, every key written out: saved beside datasets and checkpoints.
    pub fn to_toml_string(&self) -> String {
        toml::to_string(self).expect("a validated config always serialises")
    }

    /// A stable 64-bit fingerprint (FNV-1a) of the world: checkpoints and datasets record it so a
    /// mismatched world is caught before a network or a file is used with it.
    pub fn world_hash(&self) -> u64 {
        let text = toml::to_string(&self.world).expect("a world config always serialises");
        text.bytes().fold(0xcbf2_9ce4_8422_2325u64, |h, b| {
            (h ^ b as u64).wrapping_mul(0x100_0000_01b3)
        })
    }

    /// The task called `name`.
    pub fn task(&self, name: &str) -> Result<&TaskConfig, ConfigError> {
        self.tasks
            .iter()
            .find(|t| t.name == name)
            .ok_or_else(|| ConfigError::UnknownTask {
                origin: self.origin.clone(),
                name: name.to_string(),
                known: self
                    .tasks
                    .iter()
                    .map(|t| t.name.as_str())
                    .collect::<Vec<_>>()
                    .join(", "),
            })
    }

    /// The index of the task called `name` in `tasks`, its id in datasets and payloads.
    pub fn task_id(&self, name: &str) -> Result<usize, ConfigError> {
        let task = self.task(name)?;
        Ok(self
            .tasks
            .iter()
            .position(|t| std::ptr::eq(t, task))
            .expect("found above"))
    }

    pub fn tasks_with_role(&self, role: TaskRole) -> impl Iterator<Item = &TaskConfig> {
        self.tasks.iter().filter(move |t| t.role == role)
    }

    /// Checks every constraint a config must meet beyond its types: the rules its sections
    /// declare on their fields, then the checks across fields. The error is the first broken.
    pub fn validate(&self) -> Result<(), ConfigError> {
        self.check().map_err(|broken| broken.at(&self.origin))
    }

    /// What [`Config::validate`] checks, the first broken check without the config's origin.
    fn check(&self) -> Result<(), Broken> {
        garde::Validate::validate(self).map_err(first_broken)?;
        self.world.check_layout()?;
        self.check_tasks()?;
        self.check_n_step()?;
        self.tunnel.check_hosts()?;
        self.tunnel.check_security()?;
        self.check_reproduce_seeds()?;
        self.check_limits()?;
        self.check_planner_memory()
    }

    /// Every task's name is its own, and its rain fits the grid.
    fn check_tasks(&self) -> Result<(), Broken> {
        let cells = self.world.grid_cells;
        for (i, t) in self.tasks.iter().enumerate() {
            if t.name.is_empty() || self.tasks[..i].iter().any(|o| o.name == t.name) {
                let expected = "a non-empty name no other task has";
                return Err(Broken::new(format!("tasks[{i}].name"), &t.name, expected));
            }
            let outside =
                |r: &RainZone| r.x0 > r.x1 || r.y0 > r.y1 || r.x1 >= cells || r.y1 >= cells;
            if let Some(r) = t.rain.filter(outside) {
                let expected =
                    format!("a rectangle inside the grid: x0 <= x1 < {cells}, y0 <= y1 < {cells}");
                return Err(Broken::new(format!("tasks[{i}].rain"), &r, expected));
            }
            if t.rain_moves_every.is_some() && t.rain.is_none() {
                let (key, value) = (format!("tasks[{i}].rain_moves_every"), &t.rain_moves_every);
                return Err(Broken::new(key, value, "a `rain` zone to move"));
            }
        }
        Ok(())
    }

    /// The online agent's return looks at most one episode ahead.
    fn check_n_step(&self) -> Result<(), Broken> {
        let (n, horizon) = (self.collect.dqn_n_step, self.world.horizon);
        match (1..=horizon as usize).contains(&n) {
            true => Ok(()),
            false => Err(Broken::new(
                "collect.dqn_n_step",
                &n,
                format!("a step count in [1, world.horizon = {horizon}]"),
            )),
        }
    }

    /// Seed s of a reproduction collects with `collect.seed + s`, which TOML must hold.
    fn check_reproduce_seeds(&self) -> Result<(), Broken> {
        let seeds = self.reproduce.seeds;
        let last = (seeds as u64)
            .checked_sub(1)
            .map(|s| s.checked_add(self.collect.seed));
        match last {
            Some(Some(last)) if last <= i64::MAX as u64 => Ok(()),
            _ => Err(Broken::new(
                "reproduce.seeds",
                &seeds,
                format!(
                    "at least 1, with collect.seed + seeds - 1 at most {}",
                    i64::MAX
                ),
            )),
        }
    }

    /// The planner's search fits its memory bound.
    fn check_planner_memory(&self) -> Result<(), Broken> {
        let (p, w) = (&self.planner, &self.world);
        let need = p.memory_bytes(w);
        if need <= (p.max_memory_mib as u128) << 20 {
            return Ok(());
        }
        let expected = format!(
            "a search that fits planner.max_memory_mib = {} MiB; with world.horizon = {} and \
             world.devices = {} it needs {} MiB",
            p.max_memory_mib,
            w.horizon,
            w.devices,
            need >> 20
        );
        Err(Broken::new("planner.beam_width", &p.beam_width, expected))
    }

    /// Checks the `[reproduce]` keys that refer to `[[tasks]]` and `[collect]`: run by
    /// `uavmeta reproduce` only, so that other commands take configs without such tasks.
    pub fn validate_reproduce(&self) -> Result<(), ConfigError> {
        self.check_reproduce()
            .map_err(|broken| broken.at(&self.origin))
    }

    /// What [`Config::validate_reproduce`] checks.
    fn check_reproduce(&self) -> Result<(), Broken> {
        let p = &self.reproduce;
        let meta_train = self.tasks_with_role(TaskRole::MetaTrain).count();
        let of_meta_train = format!("{meta_train} tasks with role = \"meta-train\"");
        if p.meta_tasks > meta_train {
            let expected = format!("at most the {of_meta_train}");
            return Err(Broken::new("reproduce.meta_tasks", &p.meta_tasks, expected));
        }
        if p.task_counts.iter().any(|&n| n > meta_train) {
            let expected = format!("counts of at most the {of_meta_train}");
            return Err(Broken::new(
                "reproduce.task_counts",
                &p.task_counts,
                expected,
            ));
        }
        let unseen = |t: &TaskConfig| t.name == p.unseen_task && t.role == TaskRole::MetaTest;
        if !self.tasks.iter().any(unseen) {
            let expected = "the name of a task with role = \"meta-test\"";
            return Err(Broken::new(
                "reproduce.unseen_task",
                &p.unseen_task,
                expected,
            ));
        }
        let most = p.shots.iter().copied().chain([p.main_shots]).max();
        let transitions = self.collect.transitions;
        if most.is_some_and(|most| most > transitions) {
            return Err(Broken::new(
                "reproduce.shots / reproduce.main_shots",
                &(&p.shots, p.main_shots),
                format!(
                    "at most collect.transitions = {transitions}, the size of each task's dataset"
                ),
            ));
        }
        Ok(())
    }
}

/// Applies one `KEY=VALUE` override to the parsed document. `KEY` is dotted (`world.devices`);
/// a numeric part indexes an array of tables (`tasks.0.lambda`).
fn apply_override(
    doc: &mut toml_edit::DocumentMut,
    file: &str,
    assignment: &str,
) -> Result<(), ConfigError> {
    let source = format!("{file}: --set {assignment}");
    let err = |message: String| ConfigError::Parse {
        origin: source.clone(),
        message,
    };
    let (key, raw) = assignment
        .split_once('=')
        .ok_or_else(|| err("expected KEY=VALUE, e.g. world.devices=20".into()))?;
    let key = key.trim();
    let raw = raw.trim();
    let value = raw
        .parse::<toml_edit::Value>()
        .unwrap_or_else(|_| toml_edit::Value::from(raw));
    let parts: Vec<&str> = key.split('.').collect();
    if parts.iter().any(|p| p.is_empty()) {
        return Err(err(format!(
            "key `{key}`: expected dotted names such as world.devices"
        )));
    }
    let (last, path) = parts.split_last().expect("split yields at least one part");
    let mut table: &mut dyn toml_edit::TableLike = doc.as_table_mut();
    let mut steps = path.iter().peekable();
    while let Some(part) = steps.next() {
        if !table.contains_key(part) {
            table.insert(part, toml_edit::Item::Table(toml_edit::Table::new()));
        }
        let item = table.get_mut(part).expect("inserted above");
        let index = steps.peek().and_then(|p| p.parse::<usize>().ok());
        table = match index {
            Some(index) => {
                steps.next();
                let tables = item.as_array_of_tables_mut().ok_or_else(|| {
                    err(format!(
                        "key `{key}`: `{part}` is not a list of tables to index"
                    ))
                })?;
                let len = tables.len();
                tables.get_mut(index).ok_or_else(|| {
                    err(format!(
                        "key `{key}`: index {index} is out of range; `{part}` has {len} entries"
                    ))
                })?
            }
            None => item
                .as_table_like_mut()
                .ok_or_else(|| err(format!("key `{key}`: `{part}` is not a table")))?,
        };
    }
    if last.parse::<usize>().is_ok() {
        return Err(err(format!("key `{key}`: cannot replace a whole table")));
    }
    table.insert(last, toml_edit::Item::Value(value));
    Ok(())
}

// Resource limits (issue #31): what one config may ask of a machine, whatever the machine. The
// launcher also checks a config against the machine it runs on before starting anything
// (`uavmeta_meta::launch::resources`); these caps keep every estimate far from overflow and a
// typo (a batch of 10 000 000) from reaching any process.

/// Most tasks in `[[tasks]]`: each has a dataset file, services and actors of its own.
pub const MAX_TASKS: usize = 64;
/// Most actors of a run on one host, tasks x `collect.actors_per_task`.
pub const MAX_ACTORS: usize = 256;
/// Largest `run.batch_size`: an actor's shared memory grows with batch x subscriber buffer.
pub const MAX_BATCH_SIZE: usize = 16_384;
/// Largest `run.subscriber_buffer` (and `run.control_buffer`).
pub const MAX_SUBSCRIBER_BUFFER: usize = 4_096;
/// Most entries of a world's power table, grid_cells^2 x K: two tables of 8 bytes an entry,
/// 256 MiB, in every process that builds the world.
pub const MAX_POWER_TABLE: u64 = 1 << 24;

impl Config {
    /// The resource caps above that span sections (each section caps its own fields).
    fn check_limits(&self) -> Result<(), Broken> {
        let tasks = self.tasks.len();
        if tasks > MAX_TASKS {
            return Err(Broken::new(
                "tasks",
                &tasks,
                format!("at most {MAX_TASKS} tasks"),
            ));
        }
        let per_task = self.collect.actors_per_task;
        if tasks * per_task > MAX_ACTORS {
            let expected =
                format!("at most {MAX_ACTORS} actors in all, {tasks} tasks x actors_per_task");
            return Err(Broken::new("collect.actors_per_task", &per_task, expected));
        }
        let w = &self.world;
        let cells = u64::from(w.grid_cells).pow(2);
        let table = cells * w.devices as u64;
        if table > MAX_POWER_TABLE {
            let expected = format!(
                "grid_cells^2 x devices at most {MAX_POWER_TABLE} power-table entries (256 MiB in \
                 every process); {cells} cells x {} devices is {table}",
                w.devices
            );
            return Err(Broken::new("world.grid_cells", &w.grid_cells, expected));
        }
        Ok(())
    }
}

/// Whether a Zenoh endpoint (`PROTOCOL/ADDRESS:PORT`) names a loopback address, which only this
/// host's own processes can reach.
pub fn is_loopback_endpoint(endpoint: &str) -> bool {
    let address = endpoint.split_once('/').map_or(endpoint, |(_, a)| a);
    let host = match address.rsplit_once(':') {
        Some((host, _port)) => host,
        None => address,
    };
    let host = host.trim_start_matches('[').trim_end_matches(']');
    host == "localhost"
        || host
            .parse::<std::net::IpAddr>()
            .is_ok_and(|ip| ip.is_loopback())
}

// The tunnel's security (issue #31): secure by default.
impl TunnelConfig {
    /// Hosts to wait for need a tunnel to come through.
    fn check_hosts(&self) -> Result<(), Broken> {
        match self.wait_for_hosts.is_empty() || !self.listen.is_empty() {
            true => Ok(()),
            false => Err(Broken::new(
                "tunnel.wait_for_hosts",
                &self.wait_for_hosts,
                "no hosts while tunnel.listen is empty (no tunnel to wait through)",
            )),
        }
    }

    /// A `tls/` endpoint needs the CA, certificate and key; any other beyond loopback is refused,
    /// since it would let whoever reaches it join the run, unauthenticated and in clear.
    fn check_security(&self) -> Result<(), Broken> {
        if self.listen.is_empty() {
            return Ok(());
        }
        if self.listen.starts_with("tls/") {
            return self.check_tls_files();
        }
        match is_loopback_endpoint(&self.listen) {
            true => Ok(()),
            false => Err(Broken::new(
                "tunnel.listen",
                &self.listen,
                "a loopback address, or a tls/ endpoint such as tls/0.0.0.0:7447 with tunnel.ca, \
                 tunnel.certificate and tunnel.private_key set: any other would let every host \
                 that reaches it join the run, unauthenticated and unencrypted. Make the files \
                 with `uavmeta tunnel certs --dir DIR --host NAME --address ADDRESS` \
                 (docs/REMOTE.md)",
            )),
        }
    }

    /// A `tls/` endpoint's CA, certificate and key are all named.
    fn check_tls_files(&self) -> Result<(), Broken> {
        let files = [
            ("tunnel.ca", &self.ca),
            ("tunnel.certificate", &self.certificate),
            ("tunnel.private_key", &self.private_key),
        ];
        match files
            .into_iter()
            .find(|(_, path)| path.as_os_str().is_empty())
        {
            None => Ok(()),
            Some((key, path)) => Err(Broken::new(
                key,
                path,
                "a PEM file for the tls/ endpoint of tunnel.listen (`uavmeta tunnel certs` makes \
                 the run's CA and host certificates)",
            )),
        }
    }
}
