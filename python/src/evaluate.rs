//! Scoring a policy as the tables and the command line do, by the world crate's own evaluation
//! (`uavmeta_world::rollout`): the same worlds ([`evaluation_worlds`]: one per start cell where
//! the world is deterministic, fixed Monte-Carlo episodes where the rain moves; or
//! [`episode_worlds`], as `uavmeta env rollout` without `--exact`), the same episode metrics and
//! the same summaries (`PolicyMetrics`), so the figures equal the command line's to the digit.
//!
//! - [`evaluate_spec`]: a policy the world crate knows by its `--policy` name (random, stalest,
//!   greedy, planner, eps:P, actions:FILE), run in Rust episode after episode exactly as
//!   `uavmeta env rollout --policy NAME` runs it.
//! - [`Evaluation`]: every evaluation world stepped in lockstep with actions from Python, for a
//!   policy written in Python (a Q-network, an SB3 model): the caller asks for the observations,
//!   hands back one action per world, T times. Each world's episode is its own, so a
//!   deterministic policy scores as it would one episode at a time.

use numpy::{IntoPyArray, PyArray2, PyArrayMethods, PyReadonlyArray1};
use pyo3::exceptions::{PyRuntimeError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::PyDict;
use uavmeta_proto::config::{Config, TaskConfig};
use uavmeta_proto::resources::{self, Job};
use uavmeta_proto::stats::{EpisodeMetrics, Estimate, PolicyMetrics};
use uavmeta_world::heuristics::PolicySpec;
use uavmeta_world::rollout::{episode_worlds, evaluation_worlds, run_episode, EpisodeTally};
use uavmeta_world::world::World;

use crate::worlds::{write_observation, Worlds};

/// The worlds of one evaluation: `exact` as `--exact` asks, else `episodes` Monte-Carlo ones.
fn worlds_of(
    config: &Config,
    task: &TaskConfig,
    episodes: usize,
    seed: u64,
    exact: bool,
) -> Vec<World> {
    match exact {
        true => evaluation_worlds(&config.world, task, episodes, seed),
        false => episode_worlds(&config.world, task, episodes, seed).collect(),
    }
}

/// Refuses an evaluation of `episodes` episodes (`exact` as [`worlds_of`] takes it, with the
/// planner's search where `planner`) that is empty, or that does not fit the memory the process
/// may use by the one estimate of `uavmeta_proto::resources`: the worlds [`worlds_of`] would
/// build, and their table of steps as `learner.eval_episodes` of that many; the error names
/// `episodes` and the keys behind the estimate.
fn check_evaluation(
    config: &Config,
    task: &TaskConfig,
    episodes: usize,
    exact: bool,
    planner: bool,
) -> PyResult<()> {
    if episodes == 0 {
        return Err(PyValueError::new_err(
            "episodes = 0: expected at least 1 episode",
        ));
    }
    let worlds = resources::evaluation_worlds(config, task, episodes, exact);
    let mut evaluated = config.clone();
    evaluated.learner.eval_episodes = usize::try_from(worlds).unwrap_or(usize::MAX);
    let job = Job::Python {
        worlds,
        evaluation: true,
        planner,
    };
    resources::check_memory(&evaluated, job).map_err(|e| {
        let planner = if planner {
            "policy = \"planner\" with "
        } else {
            ""
        };
        PyValueError::new_err(format!("{planner}episodes = {episodes}: {e}"))
    })
}

/// Evaluates the policy `spec` (a `--policy` spelling the world crate builds) on the task env
/// `env` of `worlds` runs, its randomness seeded by `seed` as `--seed` seeds it. Returns the
/// dict of [`results`].
#[pyfunction]
#[pyo3(signature = (worlds, spec, *, env=0, episodes, seed, exact))]
pub fn evaluate_spec<'py>(
    py: Python<'py>,
    worlds: PyRef<'py, Worlds>,
    spec: &str,
    env: usize,
    episodes: usize,
    seed: u64,
    exact: bool,
) -> PyResult<Bound<'py, PyDict>> {
    let (config, task) = worlds.config_and_task_of(env)?;
    let parsed: PolicySpec = spec
        .parse()
        .map_err(|e| PyValueError::new_err(format!("policy = {spec:?}: {e}")))?;
    let planner = matches!(parsed, PolicySpec::Planner);
    check_evaluation(config, &task, episodes, exact, planner)?;
    let mut evaluation = worlds_of(config, &task, episodes, seed, exact);
    let steps = evaluation.len() * config.world.horizon as usize;
    let (starts, runs) = py
        .detach(|| {
            // Built here: a boxed policy does not cross threads, the spec does.
            let mut policy = parsed.build(config, seed, Some(steps))?;
            let starts = evaluation.iter().map(start_of).collect::<Vec<_>>();
            let runs = evaluation
                .iter_mut()
                .map(|world| run_episode(world, policy.as_mut()))
                .collect::<Vec<_>>();
            Ok((starts, runs))
        })
        .map_err(|e: uavmeta_world::heuristics::PolicyError| {
            PyValueError::new_err(format!("policy = {spec:?}: {e}"))
        })?;
    results(py, &starts, &runs)
}

/// The cell world's next episode starts from (its reset draws it, so a clone is reset).
fn start_of(world: &World) -> (u32, u32) {
    let mut w = world.clone();
    w.reset();
    w.uav()
}

/// A dict of the per-episode figures (arrays `start` (E, 2), `ret`, `aoi`, `power_mw`,
/// `outages`) and their summaries (`mean`: each figure's (mean, ci95)), as `PolicyMetrics`
/// computes them for the command line.
fn results<'py>(
    py: Python<'py>,
    starts: &[(u32, u32)],
    runs: &[EpisodeMetrics],
) -> PyResult<Bound<'py, PyDict>> {
    let out = PyDict::new(py);
    let flat: Vec<i64> = starts
        .iter()
        .flat_map(|&(x, y)| [x as i64, y as i64])
        .collect();
    out.set_item("start", flat.into_pyarray(py).reshape([starts.len(), 2])?)?;
    let column = |f: fn(&EpisodeMetrics) -> f64| runs.iter().map(f).collect::<Vec<f64>>();
    out.set_item("ret", column(|e| e.ret).into_pyarray(py))?;
    out.set_item("aoi", column(|e| e.aoi).into_pyarray(py))?;
    out.set_item("power_mw", column(|e| e.power_mw).into_pyarray(py))?;
    let outages: Vec<i64> = runs.iter().map(|e| e.outages as i64).collect();
    out.set_item("outages", outages.into_pyarray(py))?;
    let m = PolicyMetrics::from_episodes(runs);
    let pair = |e: Estimate| (e.mean, e.ci95);
    let mean = PyDict::new(py);
    mean.set_item("ret", pair(m.ret))?;
    mean.set_item("aoi", pair(m.aoi))?;
    mean.set_item("power_mw", pair(m.power_mw))?;
    mean.set_item("outages", pair(m.outages))?;
    out.set_item("mean", mean)?;
    Ok(out)
}

/// Every evaluation world of one task stepped in lockstep by actions from Python.
#[pyclass(module = "uavmeta._uavmeta")]
pub struct Evaluation {
    worlds: Vec<World>,
    tallies: Vec<EpisodeTally>,
    starts: Vec<(u32, u32)>,
    normalised: bool,
    t: u32,
    horizon: u32,
    action_count: usize,
}

#[pymethods]
impl Evaluation {
    /// The evaluation worlds of the task env `env` of `worlds` runs (`exact`: as `--exact`),
    /// each reset for its episode; observations come as `worlds` gives them (raw or normalised).
    #[new]
    #[pyo3(signature = (worlds, *, env=0, episodes, seed, exact))]
    fn new(
        worlds: PyRef<'_, Worlds>,
        env: usize,
        episodes: usize,
        seed: u64,
        exact: bool,
    ) -> PyResult<Self> {
        let (config, task) = worlds.config_and_task_of(env)?;
        check_evaluation(config, &task, episodes, exact, false)?;
        let mut evaluation = worlds_of(config, &task, episodes, seed, exact);
        evaluation.iter_mut().for_each(World::reset);
        let starts = evaluation.iter().map(World::uav).collect();
        Ok(Self {
            tallies: vec![EpisodeTally::default(); evaluation.len()],
            worlds: evaluation,
            starts,
            normalised: worlds.normalised(),
            t: 0,
            horizon: config.world.horizon,
            action_count: config.world.layout().action_count(),
        })
    }

    /// The (E, 2 + K) observations of every world at step `t`.
    fn observations<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArray2<f32>>> {
        let (e, d) = (self.worlds.len(), self.worlds[0].observation().len());
        let mut obs = vec![0f32; e * d];
        for (world, row) in self.worlds.iter().zip(obs.chunks_exact_mut(d)) {
            write_observation(world, self.normalised, row);
        }
        obs.into_pyarray(py).reshape([e, d])
    }

    /// Steps world i with `actions[i]`, one action index per world.
    fn step(&mut self, py: Python<'_>, actions: PyReadonlyArray1<'_, i64>) -> PyResult<()> {
        if self.t >= self.horizon {
            return Err(PyRuntimeError::new_err(
                "the evaluation's episodes have ended: read results()",
            ));
        }
        let actions = actions.as_slice().map_err(|e| {
            PyValueError::new_err(format!("actions: {e}: expected a contiguous array"))
        })?;
        let e = self.worlds.len();
        if actions.len() != e {
            return Err(PyValueError::new_err(format!(
                "the policy returned {} actions: expected one per evaluation episode, {e}",
                actions.len()
            )));
        }
        let count = self.action_count as i64;
        if let Some(i) = actions.iter().position(|a| !(0..count).contains(a)) {
            return Err(PyValueError::new_err(format!(
                "the policy's action for episode {i} = {}: expected an action index in 0..{count}",
                actions[i]
            )));
        }
        py.detach(|| {
            for ((world, tally), &a) in self.worlds.iter_mut().zip(&mut self.tallies).zip(actions) {
                tally.add(&world.step(a as usize));
            }
        });
        self.t += 1;
        Ok(())
    }

    /// The step the worlds stand at.
    #[getter]
    fn t(&self) -> u32 {
        self.t
    }

    #[getter]
    fn horizon(&self) -> u32 {
        self.horizon
    }

    /// The dict of per-episode figures and summaries, once every episode reached the horizon.
    fn results<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        if self.t < self.horizon {
            return Err(PyRuntimeError::new_err(format!(
                "the evaluation stands at step {} of {}: step it to the horizon first",
                self.t, self.horizon
            )));
        }
        let runs: Vec<EpisodeMetrics> = self.tallies.iter().map(|t| t.finish()).collect();
        results(py, &self.starts, &runs)
    }
}

/// The policies of every results table's reference rows, in order: random, stalest, greedy,
/// planner.
#[pyfunction]
pub fn reference_names() -> Vec<String> {
    uavmeta_world::heuristics::REFERENCES
        .iter()
        .map(|s| s.to_string())
        .collect()
}
