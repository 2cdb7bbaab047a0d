//! From the Python arguments (a config file, a task name, or a one-off lambda, rain zone and
//! `rain_moves_every`, plus `world.*` overrides) to the world and task they mean, exactly as the
//! CLI's `--config`, `--set`, `--task`, `--lambda` and `--rain` resolve them, so a Python env and
//! `uavmeta env rollout` with the same arguments step the same world.
//!
//! Every error is a Python exception carrying the config crate's message, which names the file or
//! override, the key and the value; errors about the one-off task name the Python argument
//! (`lam`, `rain`, `rain_moves_every`) instead of the config's `tasks[i]`.

use std::path::PathBuf;

use pyo3::exceptions::{PyFileNotFoundError, PyOSError, PyValueError};
use pyo3::prelude::*;
use pyo3::PyErr;
use uavmeta_proto::config::{Config, ConfigError, RainZone, TaskConfig};

use crate::tasks::Listed;

/// The task of docs/MODEL.md section 2 that an env gets when no task is named: the paper's unseen one.
pub const DEFAULT_LAMBDA: f64 = 300.0;

/// The origin the config crate gives the defaults, when no `config` file is named.
const DEFAULT_ORIGIN: &str = "the default config";

/// What the Python caller asked for.
#[derive(Debug, Clone, Default)]
pub struct TaskArgs {
    /// A config file; the defaults when absent.
    pub config: Option<PathBuf>,
    /// A task of the config, by name.
    pub task: Option<String>,
    /// The lambda of a one-off task.
    pub lam: Option<f64>,
    /// The one-off task's rain zone (x0, y0, x1, y1), inclusive.
    pub rain: Option<(u32, u32, u32, u32)>,
    pub rain_moves_every: Option<u32>,
    /// `KEY=VALUE` overrides in `--set` form (dotted keys, TOML values).
    pub overrides: Vec<String>,
}

/// The validated config and the task the arguments name.
pub fn resolve(args: &TaskArgs) -> Result<(Config, TaskConfig), PyErr> {
    let mut config = match &args.config {
        Some(path) => Config::load(path, &args.overrides),
        None => Config::from_toml_str("", DEFAULT_ORIGIN, &args.overrides),
    }
    .map_err(config_error)?;
    match (&args.task, args.lam) {
        (Some(name), Some(lam)) => Err(PyValueError::new_err(format!(
            "task = {name:?} and lam = {lam:?}: name a task of the config, or define a one-off \
             task with lam (and rain), not both"
        ))),
        (Some(name), None) => {
            if args.rain.is_some() || args.rain_moves_every.is_some() {
                return Err(PyValueError::new_err(format!(
                    "task = {name:?}: rain and rain_moves_every define a one-off task; give \
                     them with lam, or set them in the config's task"
                )));
            }
            let task = config
                .task(name)
                .map_err(|e| PyValueError::new_err(format!("task = {name:?}: {e}")))?
                .clone();
            Ok((config, task))
        }
        (None, lam) => {
            let task = one_off(lam.unwrap_or(DEFAULT_LAMBDA), args);
            let index = match config.tasks.iter().position(|t| t.name == task.name) {
                Some(i) => {
                    config.tasks[i] = task.clone();
                    i
                }
                None => {
                    config.tasks.push(task.clone());
                    config.tasks.len() - 1
                }
            };
            config
                .validate()
                .map_err(|e| one_off_error(e, index, args))?;
            Ok((config, task))
        }
    }
}

/// The one-off task of `lam` with the caller's rain; its name says its rain and how it moves.
fn one_off(lam: f64, args: &TaskArgs) -> TaskConfig {
    let rain = args
        .rain
        .map(|(x0, y0, x1, y1)| RainZone { x0, y0, x1, y1 });
    let mut task = TaskConfig::one_off(lam, rain);
    task.rain_moves_every = args.rain_moves_every;
    if let Some(every) = args.rain_moves_every {
        task.name = format!("{}-moves-{every}", task.name);
    }
    task
}

/// A config error as the Python exception that fits: a missing file is a `FileNotFoundError`
/// naming the `config` argument, another unreadable one an `OSError`, the rest `ValueError`s,
/// each with the config crate's message, a file that is no config naming `config` too.
pub fn config_error(e: ConfigError) -> PyErr {
    match &e {
        ConfigError::Read { origin, error } if error.kind() == std::io::ErrorKind::NotFound => {
            PyFileNotFoundError::new_err(format!(
                "config = {origin:?}: no such file: expected a TOML config file (configs/default.toml, or one `uavmeta` saved beside a dataset or checkpoint)"
            ))
        }
        ConfigError::Read { origin, error } => {
            PyOSError::new_err(format!("config = {origin:?}: cannot read: {error}"))
        }
        // The file itself (an override's error names its key, and the defaults parse).
        ConfigError::Parse { origin, message }
            if origin != DEFAULT_ORIGIN && !origin.contains("(with --set") =>
        {
            PyValueError::new_err(format!("config = {origin:?}: {message}"))
        }
        _ => PyValueError::new_err(e.to_string()),
    }
}

/// As [`config_error`], naming the Python argument when the bad key is the one-off task's.
fn one_off_error(e: ConfigError, index: usize, args: &TaskArgs) -> PyErr {
    if let ConfigError::Invalid {
        key,
        value,
        expected,
        ..
    } = &e
    {
        let prefix = format!("tasks[{index}].");
        if let Some(field) = key.strip_prefix(&prefix) {
            let (argument, value) = match (field, args.rain) {
                ("lambda", _) => ("lam", value.clone()),
                ("rain", Some(rain)) => ("rain", format!("{rain:?}")),
                _ => (field, value.clone()),
            };
            return PyValueError::new_err(format!("{argument} = {value}: expected {expected}"));
        }
    }
    config_error(e)
}

/// One entry of a task list from Python: a task of the config by name, or a one-off, and its
/// device layout if not the config's.
#[derive(Debug, Clone, Default)]
pub struct TaskSpec {
    pub task: Option<String>,
    pub lam: Option<f64>,
    pub rain: Option<(u32, u32, u32, u32)>,
    pub rain_moves_every: Option<u32>,
    pub layout: Option<Layout>,
}

/// A task's own device layout: a `world.layout_seed`, or one (x, y) cell per device.
#[derive(Debug, Clone, PartialEq, FromPyObject)]
pub enum Layout {
    Seed(u64),
    Cells(Vec<(u32, u32)>),
}

impl Layout {
    /// `config` with this as its world's layout.
    fn put_in(&self, config: &mut Config) {
        match self {
            Layout::Seed(seed) => {
                config.world.layout_seed = *seed;
                config.world.device_cells = None;
            }
            Layout::Cells(cells) => {
                config.world.device_cells = Some(cells.iter().map(|&(x, y)| [x, y]).collect());
            }
        }
    }
}

/// A config's task with a layout of its own (`tasks[i].device_cells` or `layout_seed`) as the
/// world's layout instead: an env's worlds share power tables only within one world layout.
pub fn own_layout_in_world(config: &mut Config, task: &mut TaskConfig) {
    if let Some(layout) = own_layout(task) {
        layout.put_in(config);
    }
}

/// As Python writes it: the seed, or the list of cells.
impl std::fmt::Display for Layout {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Layout::Seed(seed) => write!(f, "{seed}"),
            Layout::Cells(cells) => {
                let cells: Vec<String> = cells.iter().map(|(x, y)| format!("({x}, {y})")).collect();
                write!(f, "[{}]", cells.join(", "))
            }
        }
    }
}

/// The configs of an env's device layouts: the config's own at index 0, then one per distinct
/// layout the tasks name, each validated as a whole config.
pub struct Layouts {
    pub configs: Vec<Config>,
    named: Vec<Option<Layout>>,
}

impl Layouts {
    pub fn new(base: Config) -> Self {
        Self {
            configs: vec![base],
            named: vec![None],
        }
    }

    /// The index of `layout` (None: the config's), added if new; an error names `argument`
    /// and what the world expects.
    pub fn index(&mut self, layout: Option<&Layout>, argument: &str) -> PyResult<usize> {
        if let Some(i) = self.named.iter().position(|l| l.as_ref() == layout) {
            return Ok(i);
        }
        let layout = layout.expect("the config's layout is index 0");
        let mut config = self.configs[0].clone();
        layout.put_in(&mut config);
        config.validate().map_err(|e| {
            PyValueError::new_err(format!(
                "{argument} = {layout}: {e} (a layout is a world.layout_seed or one (x, y) \
                 cell per device)"
            ))
        })?;
        self.configs.push(config);
        self.named.push(Some(layout.clone()));
        Ok(self.configs.len() - 1)
    }
}

/// The layout a config's task has of its own (`tasks[i].device_cells` or `layout_seed`), taken
/// out of it into the env's layouts, whose worlds share power tables only within one layout.
fn own_layout(task: &mut TaskConfig) -> Option<Layout> {
    match (task.device_cells.take(), task.layout_seed.take()) {
        (Some(cells), _) => Some(Layout::Cells(cells.iter().map(|c| (c[0], c[1])).collect())),
        (None, seed) => seed.map(Layout::Seed),
    }
}

/// The config of `args` and the task of every entry of `specs` (`tasks[i]` of the Python
/// argument `argument`), each resolved as [`resolve`] resolves one, its errors prefixed with the
/// entry's place; with each task, its layout's index among the returned layouts.
pub fn resolve_list(
    args: &TaskArgs,
    specs: &[TaskSpec],
    argument: &str,
) -> Result<(Layouts, Vec<Listed>), PyErr> {
    if specs.is_empty() {
        return Err(PyValueError::new_err(format!(
            "{argument} = []: expected at least one task"
        )));
    }
    let mut config = None;
    let mut tasks = Vec::with_capacity(specs.len());
    for (i, spec) in specs.iter().enumerate() {
        let one = TaskArgs {
            task: spec.task.clone(),
            lam: spec.lam,
            rain: spec.rain,
            rain_moves_every: spec.rain_moves_every,
            ..args.clone()
        };
        let (c, task) = resolve(&one).map_err(|e| {
            Python::attach(|py| {
                let message = format!("{argument}[{i}]: {}", e.value(py));
                PyErr::from_type(e.get_type(py), message)
            })
        })?;
        let mut task = task;
        let own = own_layout(&mut task);
        let layouts = config.get_or_insert_with(|| Layouts::new(c));
        let key = format!("{argument}[{i}]['layout']");
        let layout = layouts.index(spec.layout.as_ref().or(own.as_ref()), &key)?;
        tasks.push(Listed { task, layout });
    }
    Ok((config.expect("at least one task"), tasks))
}
