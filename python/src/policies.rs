//! The heuristic behaviour policies of `uavmeta_world::heuristics` as batched functions of
//! observations: each row is put into a scratch world of the env's task
//! (`World::set_observation`) and the Rust policy acts on it, so Python and
//! `uavmeta env rollout --policy NAME` choose the same actions.
//!
//! The greedy policy prices a transmission with the task's configured rain zone: an observation
//! does not say where a moving zone is now. The planner reference (`uavmeta_world::planner`)
//! plans from each row at the step `t` it is told to the horizon, with the task's `[planner]`
//! settings: exact wherever the rain does not move; it keeps its plan while the rows follow it,
//! so an episode stepped one row at a time plans once.

use numpy::{IntoPyArray, PyArray1, PyReadonlyArray2};
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;
use uavmeta_proto::resources::{self, Job};
use uavmeta_world::heuristics::{GreedyPolicy, PolicySpec, RandomPolicy, StalestPolicy};
use uavmeta_world::planner::PlannerPolicy;
use uavmeta_world::rollout::Policy;
use uavmeta_world::world::World;

use crate::value_error;
use crate::worlds::Worlds;

/// A heuristic policy for the worlds of one env's task.
#[pyclass(module = "uavmeta._uavmeta")]
pub struct Heuristic {
    name: String,
    policy: Box<dyn Policy + Send + Sync>,
    /// A world of the task in which each observation is set before the policy acts.
    world: World,
    /// Multiplies an observation entry back to its raw value: 1, or L-1 and aoi_max.
    to_raw: Vec<f32>,
    /// Largest raw value of each entry: L-1 for the cell, aoi_max for the AoI.
    max_raw: Vec<u16>,
    normalised: bool,
}

#[pymethods]
impl Heuristic {
    /// `name` is random, stalest or greedy; `worlds` gives the task; `normalised` says how the
    /// observations passed in are scaled; `seed` seeds the random policy's stream (the CLI's
    /// `--seed`).
    #[new]
    #[pyo3(signature = (name, worlds, *, normalised, seed=0))]
    fn new(name: &str, worlds: PyRef<'_, Worlds>, normalised: bool, seed: u64) -> PyResult<Self> {
        worlds.one_uav("a heuristic of uavmeta.policies")?;
        let (config, task) = worlds.config_and_task();
        let policy: Box<dyn Policy + Send + Sync> = match name {
            "random" => Box::new(RandomPolicy::new(seed)),
            "stalest" => Box::new(StalestPolicy),
            "greedy" => Box::new(GreedyPolicy),
            "planner" => {
                // The planner's search, by the one estimate of the resources check.
                let job = Job::Python {
                    worlds: 1,
                    evaluation: false,
                    planner: true,
                };
                resources::check_memory(config, job)
                    .map_err(|e| PyValueError::new_err(format!("policy = \"planner\": {e}")))?;
                Box::new(PlannerPolicy::new(&config.planner))
            }
            _ => {
                return Err(PyValueError::new_err(format!(
                    "policy = {name:?}: expected random, stalest, greedy or planner"
                )))
            }
        };
        let scale = config.world.observation_scale();
        let to_raw = if normalised {
            scale
        } else {
            vec![1.0; scale.len()]
        };
        let last_cell = (config.world.grid_cells - 1) as u16;
        let mut max_raw = vec![last_cell, last_cell];
        max_raw.resize(
            config.world.layout().observation_len(),
            config.world.aoi_max as u16,
        );
        Ok(Self {
            name: name.to_string(),
            policy,
            world: World::new(&config.world, &task, 0),
            to_raw,
            max_raw,
            normalised,
        })
    }

    /// The action index of every row of `obs`, an (N, 2 + K) float32 array, at step `t` of the
    /// episode (only the planner reads it: it plans the remaining T - t steps).
    #[pyo3(signature = (obs, t=0))]
    fn __call__<'py>(
        &mut self,
        py: Python<'py>,
        obs: PyReadonlyArray2<'py, f32>,
        t: u32,
    ) -> PyResult<Bound<'py, PyArray1<i64>>> {
        let horizon = self.world.horizon();
        if t >= horizon {
            return Err(PyValueError::new_err(format!(
                "t = {t}: expected a step of the episode, 0..{horizon}"
            )));
        }
        let d = self.to_raw.len();
        let obs = obs.as_array();
        if obs.ncols() != d {
            return Err(PyValueError::new_err(format!(
                "observations of {} values: expected 2 + K = {d}",
                obs.ncols()
            )));
        }
        let mut raw = vec![0u16; d];
        let mut actions = Vec::with_capacity(obs.nrows());
        for (r, row) in obs.rows().into_iter().enumerate() {
            for (c, &v) in row.iter().enumerate() {
                raw[c] = self.raw_value(r, c, v)?;
            }
            self.world.set_observation(&raw);
            self.world.set_t(t);
            actions.push(self.policy.act(&self.world) as i64);
        }
        Ok(actions.into_pyarray(py))
    }

    #[getter]
    fn name(&self) -> String {
        self.name.clone()
    }
}

impl Heuristic {
    /// Entry (r, c) of the observations as the raw integer the world holds, or a `ValueError`
    /// naming it if it is no observation of this world.
    fn raw_value(&self, r: usize, c: usize, v: f32) -> PyResult<u16> {
        let x = v * self.to_raw[c];
        let rounded = x.round();
        let min = if c < 2 { 0.0 } else { 1.0 };
        let max = self.max_raw[c] as f32;
        if (x - rounded).abs() > 1e-3 || !(min..=max).contains(&rounded) {
            let what = if c < 2 { "a cell coordinate" } else { "an AoI" };
            let form = match self.normalised {
                true => format!(
                    "divided by {} (the policy reads normalised observations)",
                    self.to_raw[c]
                ),
                false => "(the policy reads raw observations)".to_string(),
            };
            return Err(PyValueError::new_err(format!(
                "observations[{r}, {c}] = {v}: expected {what}, an integer in {min}..={max} {form}"
            )));
        }
        Ok(rounded as u16)
    }
}

/// `(epsilon, path)` of a `q:P:CHECKPOINT` policy spec, parsed as the command line's `--policy`
/// parses it (`uavmeta_world::heuristics::PolicySpec`); any other spec is a `ValueError`.
#[pyfunction]
pub fn checkpoint_spec(spec: &str) -> PyResult<(f64, String)> {
    match spec.parse::<PolicySpec>() {
        Ok(PolicySpec::Checkpoint { epsilon, path }) => Ok((epsilon, path.display().to_string())),
        Ok(other) => Err(PyValueError::new_err(format!(
            "policy `{spec}` is `{other}`, not a saved Q-network's q:P:CHECKPOINT"
        ))),
        Err(e) => Err(value_error(e)),
    }
}
