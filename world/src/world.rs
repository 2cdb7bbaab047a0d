//! The UAV world of one task: docs/MODEL.md section 1 (grid, devices, channel, AoI, reward) and
//! section 3 (rain zones and outages).
//!
//! Everything that depends only on the UAV's cell and the scheduled device — the power the device
//! needs, with and without rain — is computed once in [`World::new`] into per-cell tables, so a
//! [`World::step`] is two table lookups, one pass over the K AoI counters and a move: it never
//! allocates.
//!
//! Two choices the paper leaves open are made here:
//! - `power_term = "all_devices"` charges the sum over all K devices of the power each would need
//!   at the UAV's cell; when the UAV is in rain, every one of those powers is rain-attenuated (each
//!   device would transmit through the same rain), while the outage is still that of the
//!   scheduled device's transmission.
//! - A task with `rain_moves_every = N` starts every episode with its configured zone and moves
//!   it after every N-th step of the episode to a uniformly random place of the same size, drawn
//!   from the world's seeded RNG.
//!
//! A team (`world.uavs` > 1, docs/MODEL.md section 11) steps with [`World::step_team`]: every
//! UAV transmits from its cell (in outage inside rain, at a penalty drawn from a stream of its own
//! inside the task's risky region), every AoI ages, each device served without outage restarts at
//! 1 once however many UAVs served it, each UAV pays its own power, and then every UAV moves.
//! With one UAV this is the paper's step, to the bit.

use std::sync::Arc;

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::Serialize;
use uavmeta_proto::config::{PowerTerm, RainZone, RiskyRegion, TaskConfig, WorldConfig, MAX_UAVS};
use uavmeta_proto::layout::Layout;

/// A UAV's move in one step. An action index is `move * targets + target`, moves in this order.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Move {
    /// (0, +1)
    North,
    /// (0, -1)
    South,
    /// (+1, 0)
    East,
    /// (-1, 0)
    West,
    /// (0, 0)
    Hover,
}

impl Move {
    /// Every move in action-index order.
    pub const ALL: [Move; 5] = [
        Move::North,
        Move::South,
        Move::East,
        Move::West,
        Move::Hover,
    ];

    /// The move of action-index block `index` (0..5).
    pub fn from_index(index: usize) -> Move {
        Self::ALL[index]
    }

    /// This move's block in the action index, `a = index * targets + target`.
    pub fn index(self) -> usize {
        self as usize
    }
}

/// What one step did (the whole team's, where there are several UAVs).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Step {
    /// r(t) = -( sum_j delta_j A_j + (lambda / K) * sum_u P_u,mW + risky penalties ).
    pub reward: f64,
    /// The power charged in this step, in milliwatts, summed over the UAVs (rain-attenuated in
    /// outage).
    pub power_mw: f64,
    /// Transmissions that failed because their UAV was inside a rain zone.
    pub outages: u32,
    /// The risky region's penalties charged, in reward units (their expectation where the world
    /// evaluates exactly).
    pub penalty: f64,
    /// Mean over devices of A_j after the AoI update: an episode's AoI metric averages this.
    pub aoi_mean: f64,
    /// The step counter reached the horizon: the episode ends by time limit, not in a terminal
    /// state.
    pub truncated: bool,
}

/// One task's environment. A clone shares the power tables; [`World::reseed`] gives it episodes
/// of its own.
#[derive(Debug, Clone)]
pub struct World {
    grid: u32,
    horizon: u32,
    aoi_max: u16,
    delta: Vec<f64>,
    /// The one delta of every device, if they share it: the AoI cost is then delta times the
    /// integer sum of the AoI, a loop the compiler vectorises.
    uniform_delta: Option<f64>,
    /// Its observation and action layout: K, U and the idle target.
    layout: Layout,
    /// Cells a move covers.
    step_cells: u32,
    /// (move, target) of every action index, sparing the step an integer division; target K is
    /// "none".
    action_parts: Vec<(Move, u32)>,
    /// lambda / K: the reward's weight of one milliwatt.
    power_weight: f64,
    device_cells: Vec<(u32, u32)>,
    /// (r / h)^2: a device's power from d cells away is its power straight below it times
    /// 1 + (r / h)^2 d^2 (docs/MODEL.md section 1). `None` where the power term sums the devices.
    slant_per_cell2: Option<f64>,
    start_cell: Option<(u32, u32)>,
    /// Every UAV's start cell, fixed for exact evaluation of a team ([`World::with_starts`]).
    joint_start: Option<Arc<[(u32, u32)]>>,
    /// Milliwatts charged when device k is scheduled with the UAV above cell c, at `[c * K + k]`;
    /// with `power_term = "all_devices"` every k of a cell holds the cell's total. Shared by
    /// clones, so a batch of worlds of one task keeps one copy in cache.
    clear_mw: Arc<[f64]>,
    /// As `clear_mw`, with every power rain-attenuated.
    rain_mw: Arc<[f64]>,
    task_rain: Option<RainZone>,
    rain: Option<RainZone>,
    rain_moves_every: Option<u32>,
    risky: Option<RiskyRegion>,
    /// Charge the risky region's expected penalty instead of drawing it: exact evaluation.
    expected_risk: bool,
    /// 1 / (L-1), 1 / (L-1), 1 / aoi_max, ...: turns the raw observation into the network input.
    inv_scale: Vec<f32>,
    rng: ChaCha8Rng,
    /// The risky region's draws, a stream apart from `rng`'s, so that they never shift the start
    /// cells and rain moves other policies meet.
    risk_rng: ChaCha8Rng,
    t: u32,
    /// s(t) = [x_1, y_1, .., x_U, y_U, A_1..A_K]: with one UAV, its observation.
    obs: Vec<u16>,
}

/// One UAV's transmission in a step.
#[derive(Debug, Clone, Copy, Default)]
struct Sent {
    power_mw: f64,
    outage: bool,
    penalty: f64,
}

impl Sent {
    /// The team's power in milliwatts and its risky penalties.
    fn totals(sent: &[Sent]) -> (f64, f64) {
        let power_mw = sent.iter().map(|s| s.power_mw).sum();
        (power_mw, sent.iter().map(|s| s.penalty).sum())
    }
}

impl World {
    /// The world of `task` under `world`, whose episodes draw their randomness (start cells, rain
    /// moves) from `seed`. The config must have passed `Config::validate`.
    pub fn new(world: &WorldConfig, task: &TaskConfig, seed: u64) -> World {
        let k = world.devices;
        let grid = world.grid_cells;
        // The task's own layout where it has one (docs/MODEL.md section 11), else the world's.
        let device_cells = match (&task.device_cells, task.layout_seed, &world.device_cells) {
            (Some(cells), _, _) | (None, None, Some(cells)) => {
                cells.iter().map(|c| (c[0], c[1])).collect()
            }
            (None, seed, _) => draw_layout(grid, k, seed.unwrap_or(world.layout_seed)),
        };

        // docs/MODEL.md section 1, step 1: P = (2^(M/B) - 1) * sigma^2 / g0 * (h^2 + d^2), in
        // watts.
        let noise_w = 10f64.powf((world.noise_dbm - 30.0) / 10.0);
        let g0 = 10f64.powf(world.g0_db / 10.0);
        let watts_per_m2 = (2f64.powf(world.bits / world.bandwidth_hz) - 1.0) * noise_w / g0;
        // docs/MODEL.md section 3: rain multiplies the power by 10^(gamma_R * d_slant_km / 10).
        let gamma_r = world.rain_attenuation_db_per_km();
        let h2 = world.height_m * world.height_m;
        let cells = (grid as usize) * (grid as usize);
        let mut clear_mw = vec![0.0; cells * k];
        let mut rain_mw = vec![0.0; cells * k];
        for c in 0..cells {
            let (ux, uy) = (c as u32 % grid, c as u32 / grid);
            for (j, &(dx, dy)) in device_cells.iter().enumerate() {
                // Cell centres are ((i + 0.5) r, (j + 0.5) r): the half cells cancel.
                let ex = (ux as f64 - dx as f64) * world.cell_m;
                let ey = (uy as f64 - dy as f64) * world.cell_m;
                let slant2 = h2 + ex * ex + ey * ey;
                let mw = watts_per_m2 * slant2 * 1e3;
                clear_mw[c * k + j] = mw;
                rain_mw[c * k + j] = mw * 10f64.powf(gamma_r * slant2.sqrt() / 1e3 / 10.0);
            }
            if world.power_term == PowerTerm::AllDevices {
                for table in [&mut clear_mw, &mut rain_mw] {
                    let row = &mut table[c * k..(c + 1) * k];
                    let total: f64 = row.iter().sum();
                    row.fill(total);
                }
            }
        }

        let layout = world.layout();
        let span = world.observation_scale()[0];
        let mut inv_scale = vec![1.0 / span; layout.state_len()];
        layout
            .state_aoi_mut(&mut inv_scale)
            .fill(1.0 / world.aoi_max as f32);
        let delta = world.delta_per_device();
        let uniform_delta = delta.iter().all(|&d| d == delta[0]).then_some(delta[0]);
        let action_parts = (0..layout.action_count())
            .map(|a| layout.split(a))
            .map(|(mv, device)| (Move::from_index(mv), device as u32))
            .collect();
        let mut w = World {
            grid,
            horizon: world.horizon,
            aoi_max: world.aoi_max as u16,
            delta,
            uniform_delta,
            layout,
            step_cells: world.step_cells,
            action_parts,
            power_weight: task.lambda / k as f64,
            device_cells,
            slant_per_cell2: (world.power_term != PowerTerm::AllDevices)
                .then(|| (world.cell_m / world.height_m).powi(2)),
            start_cell: world.start_cell.map(|c| (c[0], c[1])),
            joint_start: None,
            clear_mw: clear_mw.into(),
            rain_mw: rain_mw.into(),
            task_rain: task.rain,
            rain: task.rain,
            rain_moves_every: task.rain_moves_every,
            risky: task.risky,
            expected_risk: false,
            inv_scale,
            rng: ChaCha8Rng::seed_from_u64(seed),
            risk_rng: risk_stream(seed),
            t: 0,
            obs: vec![0; layout.state_len()],
        };
        w.reset();
        w
    }

    /// This world under another task of the same world config and device layout (a task's own
    /// layout is not read here): the power tables are shared, not computed again (on a large
    /// grid they are most of a world's memory).
    pub fn with_task(&self, task: &TaskConfig) -> World {
        let mut w = World {
            power_weight: task.lambda / self.layout.devices() as f64,
            task_rain: task.rain,
            rain: task.rain,
            rain_moves_every: task.rain_moves_every,
            risky: task.risky,
            ..self.clone()
        };
        w.reset();
        w
    }

    /// Puts this world under another task of the same world config and layout in place, for
    /// the next reset: as [`World::with_task`] without a clone, for batched envs that draw a
    /// new task at every reset. The current episode's rain zone is left as it is until then.
    pub fn set_task(&mut self, task: &TaskConfig) {
        self.power_weight = task.lambda / self.layout.devices() as f64;
        self.task_rain = task.rain;
        self.rain_moves_every = task.rain_moves_every;
        self.risky = task.risky;
    }

    /// Puts this world on the device layout of `other`, a world of the same config but for its
    /// device cells, in place: the power tables are shared, not computed again.
    pub fn set_layout(&mut self, other: &World) {
        debug_assert_eq!(
            (self.grid, self.layout.devices()),
            (other.grid, other.layout.devices())
        );
        self.device_cells.clone_from(&other.device_cells);
        self.clear_mw = Arc::clone(&other.clear_mw);
        self.rain_mw = Arc::clone(&other.rain_mw);
    }

    /// (r / h)^2, where a device's power grows as 1 + (r / h)^2 d^2 with its distance d in cells
    /// (`None` under `power_term = "all_devices"`).
    pub(crate) fn slant_per_cell2(&self) -> Option<f64> {
        self.slant_per_cell2
    }

    /// This world with the milliwatts of scheduling device k above cell c at `table[c * K + k]`,
    /// rain or not: the world a run's shots identify (`crate::identify`), which has no rain.
    pub(crate) fn with_power_table(&self, table: Vec<f64>) -> World {
        debug_assert_eq!(table.len(), self.clear_mw.len());
        let table: Arc<[f64]> = table.into();
        World {
            clear_mw: Arc::clone(&table),
            rain_mw: table,
            ..self.clone()
        }
    }

    /// Restarts the world's random stream, so the next episodes are those of `seed`.
    pub fn reseed(&mut self, seed: u64) {
        self.rng = ChaCha8Rng::seed_from_u64(seed);
        self.risk_rng = risk_stream(seed);
    }

    /// This world charging the risky region's expected penalty, never a draw: with no moving
    /// rain, every episode from given start cells is then the same, as exact evaluation needs.
    pub fn expecting_risk(mut self) -> World {
        self.expected_risk = true;
        self
    }

    /// A new episode: every UAV's start cell (fixed, or uniform at random, UAV by UAV), every
    /// A_k = 1, t = 0, and the task's own rain zone.
    pub fn reset(&mut self) {
        let layout = self.layout();
        for u in 0..self.layout.uavs() {
            let (x, y) = match (&self.joint_start, self.start_cell) {
                (Some(cells), _) => cells[u],
                (None, Some(cell)) => cell,
                (None, None) => (
                    self.rng.random_range(0..self.grid),
                    self.rng.random_range(0..self.grid),
                ),
            };
            layout.set_uav_cell(&mut self.obs, u, (x as u16, y as u16));
        }
        layout.state_aoi_mut(&mut self.obs).fill(1);
        self.rain = self.task_rain;
        self.t = 0;
    }

    /// This world with every episode starting from `cell` (every UAV of a team there).
    pub fn with_start(mut self, cell: (u32, u32)) -> World {
        assert!(
            cell.0 < self.grid && cell.1 < self.grid,
            "start cell {cell:?} is off the {0} x {0} grid",
            self.grid
        );
        self.start_cell = Some(cell);
        self.reset();
        self
    }

    /// This world with every episode starting UAV u from `cells[u]`. Exact evaluation of a team
    /// runs one episode from each joint start.
    pub fn with_starts(mut self, cells: &[(u32, u32)]) -> World {
        assert_eq!(cells.len(), self.layout.uavs(), "one start cell per UAV");
        let grid = self.grid;
        assert!(
            cells.iter().all(|&(x, y)| x < grid && y < grid),
            "start cells {cells:?} are not all on the {grid} x {grid} grid"
        );
        self.joint_start = Some(cells.into());
        self.reset();
        self
    }

    /// Whether the task has rain, moving or not.
    pub fn has_rain(&self) -> bool {
        self.task_rain.is_some()
    }

    /// Whether every episode from given start cells is the same: no rain that moves, and no
    /// risky penalty drawn. Exact evaluation then needs one episode per start and no Monte-Carlo
    /// at all.
    pub fn is_deterministic(&self) -> bool {
        let moving_rain = self.rain_moves_every.is_some() && self.task_rain.is_some();
        let drawn_risk = self.risky.is_some() && !self.expected_risk;
        !moving_rain && !drawn_risk
    }

    /// The rain zone of each remaining step t..T of this episode, as the simulator will place it:
    /// the moves depend only on the world's random stream, never on the actions, so a clone
    /// stepped with any actions meets the same zones.
    pub fn rain_schedule(&self) -> Vec<Option<RainZone>> {
        let mut ahead = self.clone();
        let remaining = self.horizon.saturating_sub(self.t);
        (0..remaining)
            .map(|_| {
                let zone = ahead.rain;
                ahead.move_rain_after_step();
                zone
            })
            .collect()
    }

    /// Steps 1-2 for the UAV above `cell` under rain zone `zone`: the milliwatts charged for
    /// scheduling `device` (a device, or K for none: no power, no outage), and whether it is in
    /// outage. The planner's model of the world.
    pub fn transmission_at(
        &self,
        cell: (u32, u32),
        device: usize,
        zone: Option<RainZone>,
    ) -> (f64, bool) {
        if device >= self.layout.devices() {
            return (0.0, false);
        }
        let at = (cell.1 * self.grid + cell.0) as usize * self.layout.devices() + device;
        if zone.is_some_and(|z| z.contains(cell.0, cell.1)) {
            (self.rain_mw[at], true)
        } else {
            (self.clear_mw[at], false)
        }
    }

    /// The task's risky region, if it has one.
    pub fn risky_region(&self) -> Option<RiskyRegion> {
        self.risky
    }

    /// The risky region's expected penalty for a transmission to `target` from `cell`: what the
    /// exact evaluation charges (0 outside the region, with no device served, or with no region).
    pub fn expected_penalty_at(&self, cell: (u32, u32), target: usize) -> f64 {
        match self.risky {
            Some(r) if target < self.layout.devices() && r.contains(cell.0, cell.1) => {
                r.expected_penalty()
            }
            _ => 0.0,
        }
    }

    /// The cell a move of `world.step_cells` leads to from `cell` (P1b: a move stops at the
    /// grid's edge, so with one cell a move off the grid stays).
    pub fn moved(&self, cell: (u32, u32), mv: Move) -> (u32, u32) {
        let (x, y) = cell;
        let (last, s) = (self.grid - 1, self.step_cells);
        match mv {
            Move::North => (x, y.saturating_add(s).min(last)),
            Move::South => (x, y.saturating_sub(s)),
            Move::East => (x.saturating_add(s).min(last), y),
            Move::West => (x.saturating_sub(s), y),
            Move::Hover => (x, y),
        }
    }

    /// lambda / K: the reward's weight of one milliwatt.
    pub fn power_weight(&self) -> f64 {
        self.power_weight
    }

    /// The raw state s(t) = [x_1, y_1, .., x_U, y_U, A_1..A_K]: with one UAV, its observation
    /// [x_u, y_u, A_1..A_K].
    pub fn observation(&self) -> &[u16] {
        &self.obs
    }

    /// UAV u's raw observation [x_u, y_u, A_1..A_K], into `out`.
    pub fn agent_observation(&self, u: usize, out: &mut [u16]) {
        self.layout().write_observation(&self.obs, u, out);
    }

    /// The observation as the networks see it: x/(L-1), y/(L-1), A/aoi_max.
    pub fn write_normalised(&self, out: &mut [f32]) {
        assert_eq!(
            out.len(),
            self.obs.len(),
            "normalised observation buffer length"
        );
        for ((o, &raw), &inv) in out.iter_mut().zip(&self.obs).zip(&self.inv_scale) {
            *o = raw as f32 * inv;
        }
    }

    /// Puts the UAV and the AoI counters where the raw observation `obs` = [x_u, y_u, A_1..A_K]
    /// says, keeping the step counter and the rain zone: policies that read the world (the
    /// heuristics) can then act on an observation alone, as the Python package's batched
    /// policies do.
    ///
    /// Panics unless `obs` has the layout's length, the cell is on the grid and every A_k is in
    /// 1..=aoi_max; callers check untrusted observations first.
    pub fn set_observation(&mut self, obs: &[u16]) {
        assert_eq!(obs.len(), self.obs.len(), "observation length");
        let (grid, layout) = (self.grid as u16, self.layout());
        for u in 0..self.layout.uavs() {
            let (x, y) = layout.uav_cell(obs, u);
            assert!(x < grid && y < grid, "cell off the grid");
        }
        assert!(
            layout
                .state_aoi(obs)
                .iter()
                .all(|&a| (1..=self.aoi_max).contains(&a)),
            "AoI outside 1..=aoi_max"
        );
        self.obs.copy_from_slice(obs);
    }

    /// Sets the step counter: the world then stands at step `t` of its episode (the planner
    /// plans the remaining T - t steps). Panics past the horizon.
    pub fn set_t(&mut self, t: u32) {
        assert!(
            t <= self.horizon,
            "step {t} is past the horizon {}",
            self.horizon
        );
        self.t = t;
    }

    /// One step of docs/MODEL.md section 1 with action `a = move * targets + target`: the
    /// one-UAV world's step. A team steps with [`World::step_team`].
    pub fn step(&mut self, action: usize) -> Step {
        assert_eq!(self.layout.uavs(), 1, "a team steps with step_team");
        let order = self.order(action);
        // 1-2. The target transmits; in rain it is in outage and spends more.
        let sent = self.send(0, order.1 as usize);
        self.finish_step(&[order], &[sent])
    }

    /// One step of the team (docs/MODEL.md section 11), UAV u taking `actions[u]`; with one UAV,
    /// [`World::step`].
    ///
    /// Panics unless there is one action per UAV, each below the layout's action count.
    pub fn step_team(&mut self, actions: &[usize]) -> Step {
        assert_eq!(actions.len(), self.layout.uavs(), "one action per UAV");
        if let [action] = *actions {
            return self.step(action);
        }
        let mut orders = [(Move::Hover, 0u32); MAX_UAVS];
        let mut sent = [Sent::default(); MAX_UAVS];
        for (u, &action) in actions.iter().enumerate() {
            orders[u] = self.order(action);
            // 1-2. Each UAV's target transmits from its own cell.
            sent[u] = self.send(u, orders[u].1 as usize);
        }
        let uavs = self.layout.uavs();
        self.finish_step(&orders[..uavs], &sent[..uavs])
    }

    /// Steps 3-5 on the world's own state once every UAV has transmitted, and the step count.
    #[inline(always)]
    fn finish_step(&mut self, orders: &[(Move, u32)], sent: &[Sent]) -> Step {
        let (power_mw, penalty) = Sent::totals(sent);
        let mut obs = std::mem::take(&mut self.obs);
        let (reward, total) = self.advance(&mut obs, orders, sent, power_mw, penalty);
        self.obs = obs;
        self.move_rain_after_step();
        Step {
            reward,
            power_mw,
            outages: sent.iter().map(|s| u32::from(s.outage)).sum(),
            penalty,
            aoi_mean: total as f64 / self.layout.devices() as f64,
            truncated: self.t >= self.horizon,
        }
    }

    /// The (move, target) of `action`; panics past the action count.
    fn order(&self, action: usize) -> (Move, u32) {
        match self.action_parts.get(action) {
            Some(&order) => order,
            None => panic!(
                "action {action} is not below {}",
                self.layout().action_count()
            ),
        }
    }

    /// UAV u's transmission to `target` from its cell: power, outage, and the risky penalty.
    #[inline(always)]
    fn send(&mut self, u: usize, target: usize) -> Sent {
        let cell = self.uav_cell(u);
        let (power_mw, outage) = self.transmission_at(cell, target, self.rain);
        Sent {
            power_mw,
            outage,
            penalty: self.draw_penalty(cell, target),
        }
    }

    /// Counts the step and moves the rain if it is due.
    fn move_rain_after_step(&mut self) {
        self.t += 1;
        if let Some(every) = self.rain_moves_every {
            if self.t.is_multiple_of(every) {
                self.move_rain();
            }
        }
    }

    /// The risky region's penalty for a transmission to `target` from `cell`: none outside it or
    /// with no device served; inside, its expectation or a draw from the risk stream.
    fn draw_penalty(&mut self, cell: (u32, u32), target: usize) -> f64 {
        match self.risky {
            Some(r) if target < self.layout.devices() && r.contains(cell.0, cell.1) => {
                if self.expected_risk {
                    r.expected_penalty()
                } else if self.risk_rng.random_bool(r.probability) {
                    r.penalty
                } else {
                    0.0
                }
            }
            _ => 0.0,
        }
    }

    /// Steps 3-5 of docs/MODEL.md section 1 (section 11 for a team) on the raw state `obs`, each
    /// UAV's (move, target) and transmission, and the team's power and penalties, given: ages the
    /// AoI, restarts every device served without outage, computes the reward, makes the moves. Returns the reward and the sum of
    /// the AoI after the update.
    #[inline(always)]
    fn advance(
        &self,
        obs: &mut [u16],
        orders: &[(Move, u32)],
        sent: &[Sent],
        power_mw: f64,
        penalty: f64,
    ) -> (f64, u32) {
        let layout = self.layout();
        // 3. Every AoI ages by one, then each device heard from restarts at 1, once.
        let cap = self.aoi_max;
        // At most 64 devices of at most 65535 each: the sum fits in u32.
        let mut total = 0u32;
        let aoi = layout.state_aoi_mut(obs);
        for a in aoi.iter_mut() {
            *a = a.saturating_add(1).min(cap);
            total += *a as u32;
        }
        for (&(_, target), s) in orders.iter().zip(sent) {
            let Some(a) = aoi.get_mut(target as usize).filter(|_| !s.outage) else {
                continue;
            };
            total -= (*a - 1) as u32;
            *a = 1;
        }
        let weighted = match self.uniform_delta {
            Some(d) => d * total as f64,
            None => layout
                .state_aoi(obs)
                .iter()
                .zip(&self.delta)
                .map(|(&a, &d)| d * a as f64)
                .sum(),
        };

        // 4. Reward: the AoI, every UAV's power, the risky penalties.
        let reward = -(self.cost(weighted, power_mw) + penalty);

        // 5. The moves; one that would leave the grid stops at its edge (P1b).
        for (u, &(mv, _)) in orders.iter().enumerate() {
            let (x, y) = layout.uav_cell(obs, u);
            let (x, y) = self.moved((x as u32, y as u32), mv);
            layout.set_uav_cell(obs, u, (x as u16, y as u16));
        }
        (reward, total)
    }

    /// What taking `action` in the one-UAV raw observation `obs` gives, with the transmission in
    /// outage or not and charged the risky region's penalty or not: the reward, with s(t+1)
    /// written into `next`. The world's own episode is untouched, so this checks a transition
    /// someone claims this world made (`crate::validate`). `None` when `obs` is not a state of
    /// this world (length, cell off the grid, an AoI of 0) or `action` is not below the action
    /// count. Which outages and penalties are possible are [`World::possible_outages`] and
    /// [`World::possible_penalties`].
    pub fn outcome(
        &self,
        obs: &[u16],
        action: usize,
        outage: bool,
        penalised: bool,
        next: &mut [u16],
    ) -> Option<f64> {
        let &(mv, target) = self.action_parts.get(action)?;
        let (x, y) = (*obs.first()? as u32, *obs.get(1)? as u32);
        let in_state = self.layout.uavs() == 1 && obs.len() == self.layout().state_len();
        let in_state = in_state && next.len() == obs.len();
        if !in_state || x >= self.grid || y >= self.grid || Layout::aoi(obs).contains(&0) {
            return None;
        }
        let target = target as usize;
        let at = (y * self.grid + x) as usize * self.layout.devices() + target;
        let power_mw = match (target < self.layout.devices(), outage) {
            (false, _) => 0.0,
            (true, true) => self.rain_mw[at],
            (true, false) => self.clear_mw[at],
        };
        let penalty = match self.risky {
            Some(r) if penalised => r.penalty,
            _ => 0.0,
        };
        let sent = Sent {
            power_mw,
            outage,
            penalty,
        };
        next.copy_from_slice(obs);
        Some(
            self.advance(next, &[(mv, target as u32)], &[sent], power_mw, penalty)
                .0,
        )
    }

    /// Whether a transmission to `target` from cell (x, y) may have been charged the risky
    /// region's penalty: never outside it or with no device served, always at probability 1,
    /// either in between.
    pub fn possible_penalties(&self, x: u32, y: u32, target: usize) -> &'static [bool] {
        match self.risky {
            Some(r) if target < self.layout.devices() && r.contains(x, y) => match r.probability {
                p if p <= 0.0 => &[false],
                p if p >= 1.0 => &[true],
                _ => &[false, true],
            },
            _ => &[false],
        }
    }

    /// The outage values a step with index `step` (0 at an episode's start) from cell (x, y) can
    /// have: none without rain; the task's zone decides while it has not moved; either once the
    /// zone may have moved (it moves to places drawn from the world's random stream).
    pub fn possible_outages(&self, x: u32, y: u32, step: u32) -> &'static [bool] {
        match (self.task_rain, self.rain_moves_every) {
            (None, _) => &[false],
            (Some(zone), every) if every.is_none_or(|every| step < every) => {
                if zone.contains(x, y) {
                    &[true]
                } else {
                    &[false]
                }
            }
            (Some(_), _) => &[false, true],
        }
    }

    /// A_max, the cap of every AoI counter.
    pub fn aoi_max(&self) -> u16 {
        self.aoi_max
    }

    /// The fixed start cell of every episode, if the world has one.
    pub fn start_cell(&self) -> Option<(u32, u32)> {
        self.start_cell
    }

    /// The cost (minus the return) the world charges for `actions` taken from this state, on a
    /// copy: how a plan is scored.
    pub fn cost_of_actions(&self, actions: &[usize]) -> f64 {
        let mut w = self.clone();
        actions.iter().map(|&a| -w.step(a).reward).sum()
    }

    /// This step's cost -r(t) if `device` were scheduled now. The move happens after the
    /// transmission, so it does not enter; the greedy heuristic minimises this.
    pub fn cost_of(&self, device: usize) -> f64 {
        self.cost_of_from(self.uav(), device)
    }

    /// As [`World::cost_of`], for a UAV above `cell` scheduling `device` (a device, or K for
    /// none). The risky region's penalty does not enter.
    pub fn cost_of_from(&self, cell: (u32, u32), device: usize) -> f64 {
        let (power_mw, outage) = self.transmission_at(cell, device, self.rain);
        let cap = self.aoi_max;
        let aged = |a: u16| a.saturating_add(1).min(cap);
        let mut weighted: f64 = self
            .aoi()
            .iter()
            .zip(&self.delta)
            .map(|(&a, &d)| d * aged(a) as f64)
            .sum();
        if !outage && device < self.layout.devices() {
            weighted -= self.delta[device] * (aged(self.aoi()[device]) - 1) as f64;
        }
        self.cost(weighted, power_mw)
    }

    /// sum_j delta_j A_j + (lambda / K) * P_mW: the negative reward (step 4).
    fn cost(&self, weighted_aoi: f64, power_mw: f64) -> f64 {
        weighted_aoi + self.power_weight * power_mw
    }

    /// Places the rain zone uniformly at random, keeping its size.
    fn move_rain(&mut self) {
        if let Some(z) = self.rain {
            let (w, h) = (z.x1 - z.x0, z.y1 - z.y0);
            let x0 = self.rng.random_range(0..self.grid - w);
            let y0 = self.rng.random_range(0..self.grid - h);
            self.rain = Some(RainZone {
                x0,
                y0,
                x1: x0 + w,
                y1: y0 + h,
            });
        }
    }

    /// A return no policy of this task can exceed (docs/MODEL.md sections 9 and 11): each step's
    /// cost at its least. After step t, with n devices restarted at it, at most n ages are 1 and
    /// at most U (the UAVs) any older age a <= t + 1, the others t + 1: the i-th youngest is at
    /// least min(1 for i <= n, then 2, 3, .. U at a time; t + 1; A_max), and the heaviest
    /// weights take the youngest ages (rearrangement). Each UAV that transmits pays at least the
    /// least power of any device from any cell, without rain: all U of them, or with "none"
    /// (`world.idle_action`) at least the n that restart an age, n the cheapest of 0..=U.
    /// Outages and risky penalties only raise the cost.
    pub fn return_bound(&self) -> f64 {
        let mut delta = self.delta.clone();
        delta.sort_by(|a, b| b.total_cmp(a));
        let least_mw = self.clear_mw.iter().copied().fold(f64::INFINITY, f64::min);
        let cap = u32::from(self.aoi_max);
        let uavs = self.layout.uavs() as u32;
        let idle = self.layout.targets() > self.layout.devices();
        let fewest_served = if idle { 0 } else { uavs };
        let cost_serving = |t: u32, n: u32| {
            let age = |i: u32| if i < n { 1 } else { 2 + (i - n) / uavs };
            let ages = (0..).map(|i: u32| f64::from(age(i).min(t + 1).min(cap)));
            let aoi: f64 = delta.iter().zip(ages).map(|(d, a)| d * a).sum();
            let paying = if idle { n } else { uavs };
            self.cost(aoi, f64::from(paying) * least_mw)
        };
        let step = |t: u32| {
            let least = (fewest_served..=uavs).map(|n| cost_serving(t, n));
            -least.fold(f64::INFINITY, f64::min)
        };
        (1..=self.horizon).map(step).sum()
    }

    /// Steps taken in this episode.
    pub fn t(&self) -> u32 {
        self.t
    }

    /// The UAV's cell (x, y): UAV 0's in a team.
    pub fn uav(&self) -> (u32, u32) {
        self.uav_cell(0)
    }

    /// UAV u's cell (x, y).
    pub fn uav_cell(&self, u: usize) -> (u32, u32) {
        let (x, y) = self.layout().uav_cell(&self.obs, u);
        (x as u32, y as u32)
    }

    /// U.
    pub fn uavs(&self) -> usize {
        self.layout.uavs()
    }

    /// Cells a move covers.
    pub fn step_cells(&self) -> u32 {
        self.step_cells
    }

    /// A_1..A_K.
    pub fn aoi(&self) -> &[u16] {
        self.layout().state_aoi(&self.obs)
    }

    /// delta_1..delta_K.
    pub fn delta(&self) -> &[f64] {
        &self.delta
    }

    pub fn device_cells(&self) -> &[(u32, u32)] {
        &self.device_cells
    }

    /// The rain zone now (it moves during an episode if the task says so).
    pub fn rain_zone(&self) -> Option<RainZone> {
        self.rain
    }

    /// K.
    pub fn devices(&self) -> usize {
        self.layout.devices()
    }

    /// Its observation and action layout.
    pub fn layout(&self) -> Layout {
        self.layout
    }

    /// Cells per side, L.
    pub fn grid_cells(&self) -> u32 {
        self.grid
    }

    /// T.
    pub fn horizon(&self) -> u32 {
        self.horizon
    }
}

/// K distinct cells from `layout_seed` alone (a partial Fisher-Yates shuffle of the cells), so
/// every task of an experiment shares the layout whatever its own seed.
/// The risky region's own stream of a world seeded `seed`.
fn risk_stream(seed: u64) -> ChaCha8Rng {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    rng.set_stream(1);
    rng
}

fn draw_layout(grid: u32, devices: usize, layout_seed: u64) -> Vec<(u32, u32)> {
    let mut rng = ChaCha8Rng::seed_from_u64(layout_seed);
    let mut cells: Vec<u32> = (0..grid * grid).collect();
    for i in 0..devices {
        let j = rng.random_range(i..cells.len());
        cells.swap(i, j);
    }
    cells[..devices]
        .iter()
        .map(|&c| (c % grid, c / grid))
        .collect()
}
