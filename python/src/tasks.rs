//! Where each env of a [`crate::worlds::Worlds`] takes its task from: one task for all (the
//! default), a list of tasks, one per env, or a sampler that draws a new task at every reset, as
//! meta-RL training asks. A task may bring its own device layout (same K): its envs then step
//! a world of that layout, built once per layout and shared.
//!
//! A draw depends only on the world seed of the episode it starts
//! ([`uavmeta_world::rollout::episode_seed`]), never on the order envs reset in, so N envs of one
//! `Worlds` and N single envs seeded alike meet the same tasks.

use std::borrow::Cow;

use pyo3::exceptions::PyValueError;
use pyo3::PyErr;
use uavmeta_proto::config::{RainZone, TaskConfig, TaskRole};
use uavmeta_world::rollout::episode_seed;

/// A task and the index of its device layout among the env's layouts (0: the config's).
#[derive(Debug, Clone)]
pub struct Listed {
    pub task: TaskConfig,
    pub layout: usize,
}

/// Where the tasks come from.
#[derive(Debug, Clone)]
pub enum TaskSource {
    /// Env i runs `tasks[i % len]` in every episode; its task id is that index.
    Fixed(Vec<Listed>),
    /// Every reset draws one of `tasks` uniformly; the task id is its index.
    Draw(Vec<Listed>),
    /// Every reset draws lambda, a rain zone, how often it moves and a layout from [`Ranges`];
    /// the task is what the envs hold before their first reset.
    Ranges(Ranges, TaskConfig),
}

/// The parametric task distribution of `uavmeta.TaskSampler(lam=(lo, hi), ...)`.
#[derive(Debug, Clone)]
pub struct Ranges {
    /// lambda, uniform in [lo, hi].
    pub lam: (f64, f64),
    /// The chance that an episode has rain at all.
    pub rain_probability: f64,
    /// Each side of the rain zone, in cells, uniform in lo..=hi; the zone uniform on the grid.
    pub rain_size: (u32, u32),
    /// How often the zone moves, one of these uniformly (None: it stays).
    pub rain_moves_every: Vec<Option<u32>>,
    /// The device layouts to draw from uniformly, as indices among the env's layouts (one
    /// alone is not drawn).
    pub layouts: Vec<usize>,
}

/// One env's task in its current episode, as `info` and `VectorEnv.tasks` report it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Current {
    pub id: i64,
    pub lambda: f64,
    pub rain: Option<RainZone>,
    pub rain_moves_every: Option<u32>,
    /// Its device layout's index among the env's layouts (0: the config's).
    pub layout: usize,
}

impl Current {
    pub fn of(id: i64, task: &TaskConfig, layout: usize) -> Self {
        Self {
            id,
            lambda: task.lambda,
            rain: task.rain,
            rain_moves_every: task.rain_moves_every,
            layout,
        }
    }
}

/// Salts the draws of a task apart from the world's own stream of the same seed.
const TASK_SALT: u64 = 0x7461_736b_2d64_7261; // "task-dra"

/// A counter-based stream of u64s from one seed (SplitMix64 of (seed, k)).
struct Draws {
    seed: u64,
    k: usize,
}

impl Draws {
    fn next(&mut self) -> u64 {
        self.k += 1;
        episode_seed(self.seed, self.k)
    }

    /// Uniform in [0, 1).
    fn unit(&mut self) -> f64 {
        (self.next() >> 11) as f64 * (1.0 / (1u64 << 53) as f64)
    }

    /// Uniform in 0..n (n > 0).
    fn below(&mut self, n: u64) -> u64 {
        ((self.next() as u128 * n as u128) >> 64) as u64
    }
}

impl TaskSource {
    /// Whether an env's task changes at its resets.
    pub fn resamples(&self) -> bool {
        !matches!(self, TaskSource::Fixed(_))
    }

    /// The named tasks, if the source has a list.
    pub fn list(&self) -> &[Listed] {
        match self {
            TaskSource::Fixed(tasks) | TaskSource::Draw(tasks) => tasks,
            TaskSource::Ranges(..) => &[],
        }
    }

    /// The first task of the list, or the task before the first draw.
    pub fn first(&self) -> &TaskConfig {
        match self {
            TaskSource::Fixed(tasks) | TaskSource::Draw(tasks) => &tasks[0].task,
            TaskSource::Ranges(_, task) => task,
        }
    }

    /// The task of env `i` in the episode run in the world seeded `world_seed` on a grid of
    /// `grid` cells a side, its id and its layout's index.
    pub fn task(&self, i: usize, world_seed: u64, grid: u32) -> (i64, Cow<'_, TaskConfig>, usize) {
        let mut draws = Draws {
            seed: world_seed ^ TASK_SALT,
            k: 0,
        };
        match self {
            TaskSource::Fixed(tasks) => {
                let j = i % tasks.len();
                (j as i64, Cow::Borrowed(&tasks[j].task), tasks[j].layout)
            }
            TaskSource::Draw(tasks) => {
                let j = draws.below(tasks.len() as u64) as usize;
                (j as i64, Cow::Borrowed(&tasks[j].task), tasks[j].layout)
            }
            TaskSource::Ranges(r, _) => {
                let lambda = r.lam.0 + (r.lam.1 - r.lam.0) * draws.unit();
                let rain = (draws.unit() < r.rain_probability).then(|| {
                    let span = (r.rain_size.1 - r.rain_size.0 + 1) as u64;
                    let w = r.rain_size.0 + draws.below(span) as u32;
                    let h = r.rain_size.0 + draws.below(span) as u32;
                    let x0 = draws.below((grid - w + 1) as u64) as u32;
                    let y0 = draws.below((grid - h + 1) as u64) as u32;
                    RainZone {
                        x0,
                        y0,
                        x1: x0 + w - 1,
                        y1: y0 + h - 1,
                    }
                });
                let moves =
                    r.rain_moves_every[draws.below(r.rain_moves_every.len() as u64) as usize];
                let task = TaskConfig {
                    name: String::new(),
                    lambda,
                    role: TaskRole::MetaTrain,
                    rain,
                    rain_moves_every: rain.and(moves),
                    risky: None,
                    device_cells: None,
                    layout_seed: None,
                };
                // Drawn last, and only among several, so a sampler without layouts draws as
                // it did before layouts existed.
                let layout = match r.layouts[..] {
                    [one] => one,
                    ref several => several[draws.below(several.len() as u64) as usize],
                };
                // The id: the draw's own seed, 63 bits, the same for the same env seed and episode.
                ((world_seed >> 1) as i64, Cow::Owned(task), layout)
            }
        }
    }
}

impl Ranges {
    /// The sampler's arguments checked against a grid of `grid` cells a side; every error names
    /// the argument.
    pub fn new(
        lam: (f64, f64),
        rain_probability: f64,
        rain_size: (u32, u32),
        rain_moves_every: Vec<Option<u32>>,
        layouts: Vec<usize>,
        grid: u32,
    ) -> Result<Self, PyErr> {
        let bad = |s: String| Err(PyValueError::new_err(s));
        let (lo, hi) = lam;
        if !(lo.is_finite() && hi.is_finite() && 0.0 <= lo && lo <= hi) {
            return bad(format!(
                "lam = ({lo:?}, {hi:?}): expected finite bounds 0 <= lo <= hi"
            ));
        }
        if !(0.0..=1.0).contains(&rain_probability) {
            return bad(format!(
                "rain_probability = {rain_probability:?}: expected a probability in [0, 1]"
            ));
        }
        let (a, b) = rain_size;
        if !(1 <= a && a <= b && b <= grid) {
            return bad(format!(
                "rain_size = ({a}, {b}): expected sides 1 <= lo <= hi <= world.grid_cells = {grid}"
            ));
        }
        if rain_moves_every.is_empty() {
            return bad(
                "rain_moves_every = []: expected at least one choice (None: the rain stays)".into(),
            );
        }
        if layouts.is_empty() {
            return bad("layouts = []: expected at least one layout (None: the config's)".into());
        }
        if let Some(Some(0)) = rain_moves_every.iter().find(|m| **m == Some(0)) {
            return bad("rain_moves_every = 0: expected at least 1 step, or None".into());
        }
        Ok(Self {
            lam,
            rain_probability,
            rain_size,
            rain_moves_every,
            layouts,
        })
    }
}
