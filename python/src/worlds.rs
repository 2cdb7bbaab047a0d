//! [`Worlds`]: N worlds, each of its own task or all of one, stepped in one call on numpy arrays
//! with the GIL released.
//!
//! **Tasks** come from a [`TaskSource`]: one task for all envs, a list (env i runs task
//! `i % len`), or a sampler that draws env i's task afresh at each of its resets from the world
//! seed of the episode it starts (so the draw is reproducible and independent of the order envs
//! reset in). Every step reports each env's task id and lambda. A task may bring its own device
//! layout (the same number of devices): its envs step that layout's power tables, built once
//! per layout and shared (`World::set_layout`).
//!
//! **Seeds.** Env i keeps a base seed and an episode counter. `reset` with a seed S starts
//! episode 0 of S; every later reset without a seed (including an autoreset) starts the next
//! episode. Episode e of base S runs in the world seeded [`uavmeta_world::rollout::episode_seed`]
//! `(S, e)`, exactly as `uavmeta env rollout --seed S` runs its episode e, so the CLI and Python
//! meet the same start cells and rain moves.
//!
//! **Autoreset** is Gymnasium 1.x's next-step mode: the step after env i reaches its horizon
//! ignores env i's action, resets it and reports reward 0, not truncated, and no info for it.

use std::path::PathBuf;
use uavmeta_proto::resources::{self, Job};

use numpy::{
    IntoPyArray, PyArray1, PyArray2, PyArray3, PyArrayMethods, PyReadonlyArray1, PyReadonlyArray2,
    PyUntypedArrayMethods,
};
use pyo3::exceptions::{PyIndexError, PyRuntimeError, PyValueError};
use pyo3::prelude::*;
use uavmeta_proto::config::{Config, TaskConfig, MAX_UAVS};
use uavmeta_world::rollout;
use uavmeta_world::world::World;

use crate::task::{
    own_layout_in_world, resolve, resolve_list, Layout, Layouts, TaskArgs, TaskSpec,
};
use crate::tasks::{Current, Listed, Ranges, TaskSource};

/// The world seed of episode `episode` of base seed `seed`: the one `uavmeta env rollout --seed`
/// gives its episode `episode`.
#[pyfunction]
pub fn episode_seed(seed: u64, episode: usize) -> u64 {
    rollout::episode_seed(seed, episode)
}

/// The most envs one `Worlds` holds: a step's arrays are then about 1 GiB at K = 10.
const MAX_ENVS: usize = 1 << 24;

/// N worlds (see the module doc for tasks, seeds and autoreset).
#[pyclass(module = "uavmeta._uavmeta")]
pub struct Worlds {
    worlds: Vec<World>,
    base_seeds: Vec<u64>,
    episodes: Vec<usize>,
    /// Env i reached its horizon in the last step: the next step resets it.
    pending_reset: Vec<bool>,
    /// Envs never reset: a batched step refuses to run while any is left.
    never_reset: usize,
    reset_once: Vec<bool>,
    /// Where each env's task comes from, and the task it runs now.
    source: TaskSource,
    current: Vec<Current>,
    /// Observations as the networks see them (x/(L-1), y/(L-1), A/aoi_max) instead of raw.
    normalised: bool,
    /// The config of each device layout the tasks use (the config's own first) and a world of
    /// it whose power tables the envs of that layout share.
    layouts: Vec<(Config, World)>,
    /// The first task: the one of every env unless a list or a sampler gives others.
    task: TaskConfig,
}

/// Python's form of a task list entry: (task name, lam, rain, rain_moves_every, layout).
type TaskTuple = (
    Option<String>,
    Option<f64>,
    Option<(u32, u32, u32, u32)>,
    Option<u32>,
    Option<Layout>,
);

/// Python's form of a parametric sampler: (lam range, rain probability, rain side range, the
/// choices of rain_moves_every, the choices of layout).
type RangesTuple = (
    (f64, f64),
    f64,
    (u32, u32),
    Vec<Option<u32>>,
    Vec<Option<Layout>>,
);

/// What one batched step returns, one entry per env.
#[derive(Default)]
struct StepOut {
    obs: Vec<f32>,
    reward: Vec<f64>,
    truncated: Vec<bool>,
    aoi: Vec<f64>,
    power_mw: Vec<f64>,
    /// The step's outages, one a UAV at most.
    outages: Vec<i64>,
    /// Each UAV's target: a device, or K for none (N x U).
    device: Vec<i64>,
    /// The team's state (N x (2U + K)), where asked for.
    state: Vec<f32>,
    task_id: Vec<i64>,
    lam: Vec<f64>,
    layout: Vec<i64>,
    /// Env i stepped (false where it was autoreset instead): the mask of every info key.
    stepped: Vec<bool>,
}

impl Worlds {
    /// The config of the arguments, with the config's own layout.
    fn config(&self) -> &Config {
        &self.layouts[0].0
    }

    fn obs_len(&self) -> usize {
        self.config().world.layout().observation_len()
    }

    fn uavs(&self) -> usize {
        self.config().world.uavs
    }

    /// The length of the team's state, `2U + K`.
    fn state_len(&self) -> usize {
        self.config().world.layout().state_len()
    }

    /// An error unless the worlds fly one UAV, for the calls of one UAV's env.
    pub fn one_uav(&self, call: &str) -> PyResult<()> {
        match self.uavs() {
            1 => Ok(()),
            u => Err(PyValueError::new_err(format!(
                "{call} on world.uavs = {u}: a team's envs reset and step with reset_team and \
                 step_team (uavmeta.TeamVectorEnv, uavmeta.pettingzoo.parallel_env)"
            ))),
        }
    }

    fn action_count(&self) -> usize {
        self.config().world.layout().action_count()
    }

    /// Starts env i's next episode: episode 0 of `seed` if given, else the episode after its
    /// last one.
    fn reset_env(&mut self, i: usize, seed: Option<u64>) {
        match seed {
            Some(seed) => {
                self.base_seeds[i] = seed;
                self.episodes[i] = 0;
            }
            None => self.episodes[i] += 1,
        }
        self.start_episode(i);
    }

    /// Starts episode `episodes[i]` of `base_seeds[i]` in env i, drawing its task first if the
    /// tasks are sampled.
    fn start_episode(&mut self, i: usize) {
        let world_seed = rollout::episode_seed(self.base_seeds[i], self.episodes[i]);
        if self.source.resamples() {
            let grid = self.config().world.grid_cells;
            let (id, task, layout) = self.source.task(i, world_seed, grid);
            if layout != self.current[i].layout {
                self.worlds[i].set_layout(&self.layouts[layout].1);
            }
            self.worlds[i].set_task(&task);
            self.current[i] = Current::of(id, &task, layout);
        }
        let world = &mut self.worlds[i];
        world.reseed(world_seed);
        world.reset();
        self.pending_reset[i] = false;
        if !self.reset_once[i] {
            self.reset_once[i] = true;
            self.never_reset -= 1;
        }
    }

    /// The task env i runs now, named as the config or the one-off naming names it.
    fn task_of(&self, i: usize) -> TaskConfig {
        let c = self.current[i];
        match &self.source {
            TaskSource::Fixed(tasks) | TaskSource::Draw(tasks) => tasks[c.id as usize].task.clone(),
            TaskSource::Ranges(..) => {
                let mut task = TaskConfig::one_off(c.lambda, c.rain);
                if let Some(every) = c.rain_moves_every {
                    task.name = format!("{}-moves-{every}", task.name);
                    task.rain_moves_every = Some(every);
                }
                task
            }
        }
    }

    fn write_obs(&self, i: usize, out: &mut [f32]) {
        write_observation(&self.worlds[i], self.normalised, out);
    }

    /// Env i's observations (each UAV's, U x (2 + K)) into `obs`, and the team's state into
    /// `state` unless it is empty.
    fn write_obs_and_state(&self, i: usize, obs: &mut [f32], state: &mut [f32]) {
        if state.is_empty() {
            return self.write_obs(i, obs);
        }
        self.write_obs(i, state);
        let layout = self.worlds[i].layout();
        for (u, out) in obs.chunks_exact_mut(layout.observation_len()).enumerate() {
            layout.write_observation(state, u, out);
        }
    }

    /// Steps every env with its U actions (already checked; env i's are
    /// `actions[i * U..(i + 1) * U]`), autoresetting those that reached their horizon in the
    /// previous step; writes the team's state too if `with_state`.
    fn step_all(&mut self, actions: &[i64], with_state: bool) -> StepOut {
        let (n, u, d) = (self.worlds.len(), self.uavs(), self.obs_len());
        let s = if with_state { self.state_len() } else { 0 };
        let mut out = StepOut {
            obs: vec![0.0; n * u * d],
            reward: vec![0.0; n],
            truncated: vec![false; n],
            aoi: vec![0.0; n],
            power_mw: vec![0.0; n],
            outages: vec![0; n],
            device: vec![0; n * u],
            state: vec![0.0; n * s],
            task_id: vec![0; n],
            lam: vec![0.0; n],
            layout: vec![0; n],
            stepped: vec![false; n],
        };
        let mut team = [0usize; MAX_UAVS];
        for (i, acts) in actions.chunks_exact(u).enumerate() {
            if self.pending_reset[i] {
                self.reset_env(i, None);
            } else {
                let world = &mut self.worlds[i];
                let step = match *acts {
                    [action] => world.step(action as usize),
                    _ => {
                        for (t, &a) in team.iter_mut().zip(acts) {
                            *t = a as usize;
                        }
                        world.step_team(&team[..u])
                    }
                };
                out.reward[i] = step.reward;
                out.truncated[i] = step.truncated;
                out.aoi[i] = step.aoi_mean;
                out.power_mw[i] = step.power_mw;
                out.outages[i] = step.outages as i64;
                let layout = world.layout();
                for (device, &a) in out.device[i * u..(i + 1) * u].iter_mut().zip(acts) {
                    *device = layout.device(a as usize) as i64;
                }
                out.stepped[i] = true;
                self.pending_reset[i] = step.truncated;
            }
            let obs = &mut out.obs[i * u * d..(i + 1) * u * d];
            self.write_obs_and_state(i, obs, &mut out.state[i * s..(i + 1) * s]);
            out.task_id[i] = self.current[i].id;
            out.lam[i] = self.current[i].lambda;
            out.layout[i] = self.current[i].layout as i64;
        }
        out
    }

    fn check_env(&self, i: usize) -> PyResult<()> {
        if i < self.worlds.len() {
            Ok(())
        } else {
            Err(PyIndexError::new_err(format!(
                "env {i}: expected an index below num_envs = {}",
                self.worlds.len()
            )))
        }
    }

    /// Starts a new episode in every env i (episode 0 of `seeds[i]`, or the next one where
    /// None); returns each UAV's observations (N x U x (2 + K)) and, if `with_state`, the
    /// team's states (N x (2U + K)).
    fn reset_all(
        &mut self,
        seeds: Vec<Option<u64>>,
        with_state: bool,
    ) -> PyResult<(Vec<f32>, Vec<f32>)> {
        let (n, u, d) = (self.worlds.len(), self.uavs(), self.obs_len());
        let s = if with_state { self.state_len() } else { 0 };
        if seeds.len() != n {
            return Err(PyValueError::new_err(format!(
                "seed has {} entries: expected one per env, num_envs = {n}",
                seeds.len()
            )));
        }
        let (mut obs, mut state) = (vec![0.0f32; n * u * d], vec![0.0f32; n * s]);
        for (i, seed) in seeds.into_iter().enumerate() {
            self.reset_env(i, seed);
            let o = &mut obs[i * u * d..(i + 1) * u * d];
            self.write_obs_and_state(i, o, &mut state[i * s..(i + 1) * s]);
        }
        Ok((obs, state))
    }

    /// Every env reset once, and every action of a batch in range (the first bad one named).
    fn check_batch(&self, actions: &[i64]) -> PyResult<()> {
        if self.never_reset > 0 {
            let i = self.reset_once.iter().position(|r| !r).unwrap_or(0);
            return Err(PyRuntimeError::new_err(format!(
                "env {i} was never reset: call reset() before step()"
            )));
        }
        let count = self.action_count() as i64;
        if let Some(i) = actions.iter().position(|a| !(0..count).contains(a)) {
            let key = match self.uavs() {
                1 => format!("actions[{i}]"),
                u => format!("actions[{}, {}]", i / u, i % u),
            };
            self.check_action(&key, actions[i])?;
        }
        Ok(())
    }

    fn check_action(&self, key: &str, action: i64) -> PyResult<usize> {
        let count = self.action_count();
        if (0..count as i64).contains(&action) {
            Ok(action as usize)
        } else {
            Err(PyValueError::new_err(format!(
                "{key} = {action}: expected an action index in 0..{count} (a = move * targets + target, {} targets)",
                self.config().world.layout().targets()
            )))
        }
    }
}

/// One env's step as `UavEnv.step` returns it, before Python adds the dict, and the UAV's cell.
type StepOne<'py> = (
    Bound<'py, PyArray1<f32>>,
    f64,
    bool,
    f64,
    f64,
    bool,
    usize,
    (u32, u32),
);

/// A batched step: obs, reward, terminated, truncated, aoi, power_mw, outage, device, stepped,
/// task_id, lam, layout.
type StepBatch<'py> = (
    Bound<'py, PyArray2<f32>>,
    Bound<'py, PyArray1<f64>>,
    Bound<'py, PyArray1<bool>>,
    Bound<'py, PyArray1<bool>>,
    Bound<'py, PyArray1<f64>>,
    Bound<'py, PyArray1<f64>>,
    Bound<'py, PyArray1<bool>>,
    Bound<'py, PyArray1<i64>>,
    Bound<'py, PyArray1<bool>>,
    Bound<'py, PyArray1<i64>>,
    Bound<'py, PyArray1<f64>>,
    Bound<'py, PyArray1<i64>>,
);

/// A team's reset: each UAV's observation (N, U, 2 + K) and the team's state (N, 2U + K).
type TeamReset<'py> = (Bound<'py, PyArray3<f32>>, Bound<'py, PyArray2<f32>>);

/// A batched team step: obs (N, U, 2 + K), state (N, 2U + K), reward, truncated, aoi,
/// power_mw, outages, targets (N, U), stepped, task_id, lam, layout.
type TeamBatch<'py> = (
    Bound<'py, PyArray3<f32>>,
    Bound<'py, PyArray2<f32>>,
    Bound<'py, PyArray1<f64>>,
    Bound<'py, PyArray1<bool>>,
    Bound<'py, PyArray1<f64>>,
    Bound<'py, PyArray1<f64>>,
    Bound<'py, PyArray1<i64>>,
    Bound<'py, PyArray2<i64>>,
    Bound<'py, PyArray1<bool>>,
    Bound<'py, PyArray1<i64>>,
    Bound<'py, PyArray1<f64>>,
    Bound<'py, PyArray1<i64>>,
);

#[pymethods]
impl Worlds {
    /// `num_envs` worlds of the task that `config`, `task`, `lam`, `rain`, `rain_moves_every`
    /// and the `KEY=VALUE` `overrides` name (see `uavmeta.UavEnv`); or, given `tasks` (a list
    /// of (task name, lam, rain, rain_moves_every, layout)), env i runs `tasks[i % len]`, or
    /// with `draw=True` draws one of them at each reset; or, given `ranges`, draws a task from
    /// those ranges at each reset. A layout is a `world.layout_seed` or one (x, y) cell per
    /// device; None is the config's. Call `reset` before stepping.
    #[new]
    #[pyo3(signature = (num_envs, *, normalised=false, config=None, task=None, lam=None, rain=None, rain_moves_every=None, overrides=Vec::new(), tasks=None, draw=false, ranges=None))]
    #[allow(clippy::too_many_arguments)]
    fn new(
        num_envs: usize,
        normalised: bool,
        config: Option<PathBuf>,
        task: Option<String>,
        lam: Option<f64>,
        rain: Option<(u32, u32, u32, u32)>,
        rain_moves_every: Option<u32>,
        overrides: Vec<String>,
        tasks: Option<Vec<TaskTuple>>,
        draw: bool,
        ranges: Option<RangesTuple>,
    ) -> PyResult<Self> {
        if num_envs == 0 {
            return Err(PyValueError::new_err(
                "num_envs = 0: expected at least 1 env",
            ));
        }
        let args = TaskArgs {
            config,
            task,
            lam,
            rain,
            rain_moves_every,
            overrides,
        };
        let (layouts, source) = match (tasks, ranges) {
            (Some(_), Some(_)) => {
                return Err(PyValueError::new_err(
                    "tasks and a sampler's ranges: expected one source of tasks, not both",
                ))
            }
            (Some(list), None) => {
                let specs: Vec<TaskSpec> = list
                    .into_iter()
                    .map(|(task, lam, rain, rain_moves_every, layout)| TaskSpec {
                        task,
                        lam,
                        rain,
                        rain_moves_every,
                        layout,
                    })
                    .collect();
                let (layouts, tasks) = resolve_list(&args, &specs, "tasks")?;
                let source = match draw {
                    true => TaskSource::Draw(tasks),
                    false => TaskSource::Fixed(tasks),
                };
                (layouts, source)
            }
            (None, Some((lam, rain_probability, rain_size, moves, choices))) => {
                // Until its first reset every env holds the base task of the other arguments.
                let (mut config, mut task) = resolve(&args)?;
                own_layout_in_world(&mut config, &mut task);
                let grid = config.world.grid_cells;
                let mut layouts = Layouts::new(config);
                let choices = choices
                    .iter()
                    .enumerate()
                    .map(|(i, l)| layouts.index(l.as_ref(), &format!("layouts[{i}]")))
                    .collect::<PyResult<_>>()?;
                let ranges = Ranges::new(lam, rain_probability, rain_size, moves, choices, grid)?;
                (layouts, TaskSource::Ranges(ranges, task))
            }
            (None, None) => {
                let (mut config, mut task) = resolve(&args)?;
                own_layout_in_world(&mut config, &mut task);
                let listed = Listed { task, layout: 0 };
                (Layouts::new(config), TaskSource::Fixed(vec![listed]))
            }
        };
        let task = source.first().clone();
        // The memory estimate first, so that a size beyond the machine is refused with the keys
        // and bytes behind it; the cap then bounds a step's arrays where the machine does not say.
        let job = Job::Python {
            worlds: num_envs as u64,
            evaluation: false,
            planner: false,
        };
        for config in &layouts.configs {
            resources::check_memory(config, job)
                .map_err(|e| PyValueError::new_err(format!("num_envs = {num_envs}: {e}")))?;
        }
        if num_envs > MAX_ENVS {
            return Err(PyValueError::new_err(format!(
                "num_envs = {num_envs}: expected 1 to {MAX_ENVS} envs"
            )));
        }
        let layouts: Vec<(Config, World)> = (layouts.configs.into_iter())
            .map(|config| {
                let world = World::new(&config.world, &task, 0);
                (config, world)
            })
            .collect();
        let mut worlds = vec![layouts[0].1.clone(); num_envs];
        let mut current = vec![Current::of(0, &task, 0); num_envs];
        if let TaskSource::Fixed(tasks) = &source {
            for (i, (world, now)) in worlds.iter_mut().zip(&mut current).enumerate() {
                let Listed { task, layout } = &tasks[i % tasks.len()];
                world.set_layout(&layouts[*layout].1);
                world.set_task(task);
                *now = Current::of((i % tasks.len()) as i64, task, *layout);
            }
        }
        Ok(Self {
            worlds,
            base_seeds: vec![0; num_envs],
            episodes: vec![0; num_envs],
            // Until the first reset, a step resets first.
            pending_reset: vec![true; num_envs],
            never_reset: num_envs,
            reset_once: vec![false; num_envs],
            source,
            current,
            normalised,
            layouts,
            task,
        })
    }

    /// Starts a new episode in every env i: episode 0 of `seeds[i]`, or where that is None the
    /// episode after env i's last one; returns the (N, 2 + K) observations.
    fn reset<'py>(
        &mut self,
        py: Python<'py>,
        seeds: Vec<Option<u64>>,
    ) -> PyResult<Bound<'py, PyArray2<f32>>> {
        self.one_uav("reset")?;
        let (n, d) = (self.worlds.len(), self.obs_len());
        let (obs, _) = self.reset_all(seeds, false)?;
        obs.into_pyarray(py).reshape([n, d])
    }

    /// Starts env i's next episode (episode 0 of `seed` if given); returns its observation.
    #[pyo3(signature = (i, seed=None))]
    fn reset_one<'py>(
        &mut self,
        py: Python<'py>,
        i: usize,
        seed: Option<u64>,
    ) -> PyResult<Bound<'py, PyArray1<f32>>> {
        self.check_env(i)?;
        self.one_uav("reset_one")?;
        self.reset_env(i, seed);
        self.observation(py, i)
    }

    /// Env i's current observation, 2 + K values.
    fn observation<'py>(&self, py: Python<'py>, i: usize) -> PyResult<Bound<'py, PyArray1<f32>>> {
        self.check_env(i)?;
        self.one_uav("observation")?;
        let mut obs = vec![0.0f32; self.obs_len()];
        self.write_obs(i, &mut obs);
        Ok(obs.into_pyarray(py))
    }

    /// One step of env i: (obs, reward, truncated, aoi, power_mw, outage, device, the UAV's cell
    /// after the move). Env i must have been reset and not yet have reached its horizon.
    fn step_one<'py>(&mut self, py: Python<'py>, i: usize, action: i64) -> PyResult<StepOne<'py>> {
        self.check_env(i)?;
        self.one_uav("step_one")?;
        let action = self.check_action("action", action)?;
        if self.pending_reset[i] {
            return Err(PyRuntimeError::new_err(
                "the episode has ended (or never started): call reset() before step()",
            ));
        }
        let step = self.worlds[i].step(action);
        self.pending_reset[i] = step.truncated;
        let obs = self.observation(py, i)?;
        Ok((
            obs,
            step.reward,
            step.truncated,
            step.aoi_mean,
            step.power_mw,
            step.outages > 0,
            self.worlds[i].layout().device(action),
            self.worlds[i].uav(),
        ))
    }

    /// Steps all N envs with `actions` (N action indices) in one call, the GIL released, with
    /// next-step autoreset. Returns (obs, reward, terminated, truncated, aoi, power_mw, outage,
    /// device, stepped): `stepped` is false for the envs autoreset by this call.
    fn step<'py>(
        &mut self,
        py: Python<'py>,
        actions: PyReadonlyArray1<'py, i64>,
    ) -> PyResult<StepBatch<'py>> {
        self.one_uav("step")?;
        let (n, d) = (self.worlds.len(), self.obs_len());
        let actions = actions.as_slice().map_err(|e| {
            PyValueError::new_err(format!("actions: {e}: expected a contiguous array"))
        })?;
        if actions.len() != n {
            return Err(PyValueError::new_err(format!(
                "actions has {} entries: expected one per env, num_envs = {n}",
                actions.len()
            )));
        }
        self.check_batch(actions)?;
        let out = py.detach(|| self.step_all(actions, false));
        let outage: Vec<bool> = out.outages.iter().map(|&o| o > 0).collect();
        Ok((
            out.obs.into_pyarray(py).reshape([n, d])?,
            out.reward.into_pyarray(py),
            vec![false; n].into_pyarray(py),
            out.truncated.into_pyarray(py),
            out.aoi.into_pyarray(py),
            out.power_mw.into_pyarray(py),
            outage.into_pyarray(py),
            out.device.into_pyarray(py),
            out.stepped.into_pyarray(py),
            out.task_id.into_pyarray(py),
            out.lam.into_pyarray(py),
            out.layout.into_pyarray(py),
        ))
    }

    /// The team's `reset`, for any U: starts a new episode in every env i (episode 0 of
    /// `seeds[i]`, or the next one where None) and returns each UAV's observation
    /// (N, U, 2 + K) and the team's state (N, 2U + K).
    fn reset_team<'py>(
        &mut self,
        py: Python<'py>,
        seeds: Vec<Option<u64>>,
    ) -> PyResult<TeamReset<'py>> {
        let (n, u, d, s) = (
            self.worlds.len(),
            self.uavs(),
            self.obs_len(),
            self.state_len(),
        );
        let (obs, state) = self.reset_all(seeds, true)?;
        Ok((
            obs.into_pyarray(py).reshape([n, u, d])?,
            state.into_pyarray(py).reshape([n, s])?,
        ))
    }

    /// The team's `step`, for any U: every env i's UAVs take `actions[i]` (an (N, U) array of
    /// action indices), in one call with the GIL released and next-step autoreset. Returns
    /// (obs, state, reward, truncated, aoi, power_mw, outages, targets, stepped, task_id, lam,
    /// layout): `reward` is the team's, `targets[i, u]` UAV u's device (K for none); no env
    /// terminates.
    fn step_team<'py>(
        &mut self,
        py: Python<'py>,
        actions: PyReadonlyArray2<'py, i64>,
    ) -> PyResult<TeamBatch<'py>> {
        let (n, u, d, s) = (
            self.worlds.len(),
            self.uavs(),
            self.obs_len(),
            self.state_len(),
        );
        if actions.shape() != [n, u] {
            return Err(PyValueError::new_err(format!(
                "actions of shape {:?}: expected ({n}, {u}), one action per env and UAV",
                actions.shape()
            )));
        }
        let actions = actions.as_slice().map_err(|e| {
            PyValueError::new_err(format!("actions: {e}: expected a contiguous array"))
        })?;
        self.check_batch(actions)?;
        let out = py.detach(|| self.step_all(actions, true));
        Ok((
            out.obs.into_pyarray(py).reshape([n, u, d])?,
            out.state.into_pyarray(py).reshape([n, s])?,
            out.reward.into_pyarray(py),
            out.truncated.into_pyarray(py),
            out.aoi.into_pyarray(py),
            out.power_mw.into_pyarray(py),
            out.outages.into_pyarray(py),
            out.device.into_pyarray(py).reshape([n, u])?,
            out.stepped.into_pyarray(py),
            out.task_id.into_pyarray(py),
            out.lam.into_pyarray(py),
            out.layout.into_pyarray(py),
        ))
    }

    /// U, the UAVs of each world (`world.uavs`).
    #[getter(uavs)]
    fn uavs_py(&self) -> usize {
        self.uavs()
    }

    /// Each UAV's discrete actions: 5 moves times the targets (K devices, and "none" with
    /// `world.idle_action`).
    #[getter(action_count)]
    fn action_count_py(&self) -> usize {
        self.action_count()
    }

    /// Whether a UAV may serve no device (`world.idle_action`): target K.
    #[getter]
    fn idle_action(&self) -> bool {
        self.config().world.idle_action
    }

    /// Every UAV's cell in env i, UAV 0 first.
    fn uav_cells(&self, i: usize) -> PyResult<Vec<(u32, u32)>> {
        self.check_env(i)?;
        let w = &self.worlds[i];
        Ok((0..w.uavs()).map(|u| w.uav_cell(u)).collect())
    }

    /// Env i's task now: (task id, lambda, rain zone or None, rain_moves_every or None, name,
    /// layout index).
    #[allow(clippy::type_complexity)]
    fn task_now(
        &self,
        i: usize,
    ) -> PyResult<(
        i64,
        f64,
        Option<(u32, u32, u32, u32)>,
        Option<u32>,
        String,
        usize,
    )> {
        self.check_env(i)?;
        let c = self.current[i];
        let rain = c.rain.map(|z| (z.x0, z.y0, z.x1, z.y1));
        Ok((
            c.id,
            c.lambda,
            rain,
            c.rain_moves_every,
            self.task_of(i).name,
            c.layout,
        ))
    }

    /// Every env's task id, lambda and layout index now: three arrays of N.
    #[allow(clippy::type_complexity)]
    fn task_arrays<'py>(
        &self,
        py: Python<'py>,
    ) -> (
        Bound<'py, PyArray1<i64>>,
        Bound<'py, PyArray1<f64>>,
        Bound<'py, PyArray1<i64>>,
    ) {
        let ids: Vec<i64> = self.current.iter().map(|c| c.id).collect();
        let lams: Vec<f64> = self.current.iter().map(|c| c.lambda).collect();
        let layouts: Vec<i64> = self.current.iter().map(|c| c.layout as i64).collect();
        (
            ids.into_pyarray(py),
            lams.into_pyarray(py),
            layouts.into_pyarray(py),
        )
    }

    /// How many device layouts the envs' tasks use (1: the config's alone).
    #[getter]
    fn layout_count(&self) -> usize {
        self.layouts.len()
    }

    /// Whether env i's task changes at its resets (a sampler).
    #[getter]
    fn resamples_tasks(&self) -> bool {
        self.source.resamples()
    }

    /// How many tasks the envs run: 1 for one task, the list's length, or None for a sampler
    /// of ranges.
    #[getter]
    fn task_count(&self) -> Option<usize> {
        match &self.source {
            TaskSource::Ranges(..) => None,
            s => Some(s.list().len()),
        }
    }

    /// (base seed, episode) of env i: its episode is episode `episode` of `base seed`.
    fn seed_and_episode(&self, i: usize) -> PyResult<(u64, usize)> {
        self.check_env(i)?;
        Ok((self.base_seeds[i], self.episodes[i]))
    }

    /// Makes env i stand at the start of episode `episode` of `seed`, as `reset_one(i, seed)`
    /// and `episode` more resets would; returns its observation.
    fn reset_to<'py>(
        &mut self,
        py: Python<'py>,
        i: usize,
        seed: u64,
        episode: usize,
    ) -> PyResult<Bound<'py, PyArray1<f32>>> {
        self.check_env(i)?;
        self.base_seeds[i] = seed;
        self.episodes[i] = episode;
        self.start_episode(i);
        self.observation(py, i)
    }

    /// Env i's state for drawing: ((x, y) of the UAV, step t, the rain zone now or None, A_1..A_K).
    #[allow(clippy::type_complexity)]
    fn state(
        &self,
        i: usize,
    ) -> PyResult<((u32, u32), u32, Option<(u32, u32, u32, u32)>, Vec<u16>)> {
        self.check_env(i)?;
        let w = &self.worlds[i];
        let rain = w.rain_zone().map(|z| (z.x0, z.y0, z.x1, z.y1));
        Ok((w.uav(), w.t(), rain, w.aoi().to_vec()))
    }

    #[getter]
    fn devices(&self) -> usize {
        self.config().world.devices
    }

    #[getter]
    fn grid_cells(&self) -> u32 {
        self.config().world.grid_cells
    }

    #[getter]
    fn horizon(&self) -> u32 {
        self.config().world.horizon
    }

    #[getter]
    fn aoi_max(&self) -> u32 {
        self.config().world.aoi_max
    }

    /// The world's hash, as a checkpoint or dataset header records it: equal hashes, equal worlds.
    #[getter]
    fn world_hash(&self) -> u64 {
        self.config().world_hash()
    }

    /// Episodes of `uavmeta eval` and of the tables' evaluations (`learner.eval_episodes`).
    #[getter]
    fn eval_episodes(&self) -> usize {
        self.config().learner.eval_episodes
    }

    /// Their seed (`learner.eval_seed`).
    #[getter]
    fn eval_seed(&self) -> u64 {
        self.config().learner.eval_seed
    }

    #[getter]
    pub fn normalised(&self) -> bool {
        self.normalised
    }

    #[getter]
    fn lam(&self) -> f64 {
        self.task.lambda
    }

    #[getter]
    fn task_name(&self) -> String {
        self.task.name.clone()
    }

    /// Env i's device cells now (its task's layout).
    fn device_cells(&self, i: usize) -> PyResult<Vec<(u32, u32)>> {
        self.check_env(i)?;
        Ok(self.worlds[i].device_cells().to_vec())
    }

    /// Divisors from a raw observation to the normalised one: L-1, L-1, aoi_max, ...
    #[getter]
    fn observation_scale(&self) -> Vec<f32> {
        self.config().world.observation_scale()
    }

    /// The whole config, every key written out, with the task among its `[[tasks]]`.
    #[getter]
    fn config_toml(&self) -> String {
        self.config().to_toml_string()
    }
}

impl Worlds {
    /// The resolved config and the task env 0 runs now, for the policies and evaluations built
    /// on an env.
    pub fn config_and_task(&self) -> (&Config, TaskConfig) {
        (&self.layouts[self.current[0].layout].0, self.task_of(0))
    }

    /// The resolved config of env `i`'s layout and the task it runs now.
    pub fn config_and_task_of(&self, i: usize) -> PyResult<(&Config, TaskConfig)> {
        self.check_env(i)?;
        self.one_uav("uavmeta.evaluate")?;
        let layout = self.current[i].layout;
        Ok((&self.layouts[layout].0, self.task_of(i)))
    }
}

/// `world`'s observation into `out`, normalised or raw.
pub fn write_observation(world: &World, normalised: bool, out: &mut [f32]) {
    if normalised {
        world.write_normalised(out);
    } else {
        for (o, &v) in out.iter_mut().zip(world.observation()) {
            *o = v as f32;
        }
    }
}
