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

/// The task of docs/MODEL.md section 2 that an env gets when no task is named: the paper's unseen one.
pub const DEFAULT_LAMBDA: f64 = 300.0;

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
        None => Config::from_toml_str("", "the default config", &args.overrides),
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
            let task = config.task(name).map_err(config_error)?.clone();
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
/// each with the config crate's message.
pub fn config_error(e: ConfigError) -> PyErr {
    match &e {
        ConfigError::Read { origin, error } if error.kind() == std::io::ErrorKind::NotFound => {
            PyFileNotFoundError::new_err(format!(
                "config = {origin:?}: no such file: expected a TOML config file (configs/default.toml, or one `uavmeta` saved beside a dataset or checkpoint)"
            ))
        }
        ConfigError::Read { .. } => PyOSError::new_err(format!("config: {e}")),
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

/// One entry of a task list from Python: a task of the config by name, or a one-off.
#[derive(Debug, Clone, Default)]
pub struct TaskSpec {
    pub task: Option<String>,
    pub lam: Option<f64>,
    pub rain: Option<(u32, u32, u32, u32)>,
    pub rain_moves_every: Option<u32>,
}

/// The config of `args` and the task of every entry of `specs` (`tasks[i]` of the Python
/// argument `argument`), each resolved as [`resolve`] resolves one, its errors prefixed with the
/// entry's place.
pub fn resolve_list(
    args: &TaskArgs,
    specs: &[TaskSpec],
    argument: &str,
) -> Result<(Config, Vec<TaskConfig>), PyErr> {
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
        config.get_or_insert(c);
        tasks.push(task);
    }
    Ok((config.expect("at least one task"), tasks))
}
