//! Experiment configuration: docs/MODEL.md section 7's TOML layout with every default of
//! docs/MODEL.md sections 1-5.
//!
//! A file names only what it changes; [`Config::load`] reads it, applies `--set KEY=VALUE`
//! overrides, and validates the result. Every error names the file (or the override), the key, the
//! offending value and what was expected.
//!
//! Each section is a file of its own with its defaults and rules on its fields, saying which
//! crates read it; [`Config`] puts them together, and [`rules`] holds what the sections declare.
//! A section that only one crate outside the contract reads (`[reproduce]`) is that crate's: the
//! config keeps it as written ([`OwnedSection`]) and its owner declares and checks it
//! ([`Section`]).

use std::path::Path;

use garde::Validate;
use serde::{Deserialize, Serialize};
use smart_default::SmartDefault;

mod collect;
mod context;
mod learner;
mod meta;
mod moved;
mod planner;
pub mod rules;
mod run;
mod section;
mod task;
mod tunnel;
mod world;

pub use collect::{CollectConfig, OnlineDqnConfig};
pub use context::ContextConfig;
pub use learner::LearnerConfig;
pub use meta::MetaConfig;
pub use moved::{Fate, MOVED};
pub use planner::PlannerConfig;
pub use run::{RunConfig, MAX_DOMAIN_LEN, MAX_SUBSCRIBER_BUFFER, MAX_TRANSITIONS_PER_MESSAGE};
pub use section::{OwnedSection, Section};
pub use task::{RainZone, RiskyRegion, TaskConfig, TaskRole};
pub use tunnel::{
    is_host_name, is_loopback_endpoint, TunnelConfig, ALL_TASKS, HOST_NAME_RULE, MAX_HOSTS,
};
pub use world::{
    enumerated_starts, Delta, PowerTerm, WorldConfig, MAX_DEVICES, MAX_GRID_CELLS,
    MAX_JOINT_STARTS, MAX_UAVS, MOVES,
};

use rules::{first_broken, non_empty, Broken};
use task::default_tasks;

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
    #[error("{origin}: key `{key}` {fate}")]
    Moved {
        origin: String,
        key: String,
        fate: Fate,
    },
    #[error("{origin}: no task named `{name}`; the config defines: {known}")]
    UnknownTask {
        origin: String,
        name: String,
        known: String,
    },
}

/// One experiment: the world, its tasks, and the settings of every stage.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, SmartDefault, Validate)]
#[serde(deny_unknown_fields)]
#[garde(allow_unvalidated)]
pub struct Config {
    #[serde(default)]
    #[garde(dive)]
    pub world: WorldConfig,
    #[serde(default = "default_tasks")]
    #[default(default_tasks())]
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
    pub context: ContextConfig,
    #[serde(default)]
    #[garde(dive)]
    pub run: RunConfig,
    /// `[reproduce]`, as written: `uavmeta_reproduce` owns its keys and checks them when a
    /// reproduction starts.
    #[serde(default, skip_serializing_if = "OwnedSection::is_empty")]
    #[garde(skip)]
    pub reproduce: OwnedSection,
    #[serde(default)]
    #[garde(dive)]
    pub tunnel: TunnelConfig,
    #[serde(default)]
    #[garde(dive)]
    pub planner: PlannerConfig,
    /// Where the config was read from; not part of the TOML.
    #[serde(skip)]
    #[default("<defaults>")]
    pub origin: String,
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
        moved::check(&doc, &source_desc)?;
        let merged = doc.to_string();
        let mut config: Config = toml::from_str(&merged).map_err(|e| ConfigError::Parse {
            origin: source_desc.clone(),
            message: type_error(&merged, &e),
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
        let mut text = toml::to_string(&self.world).expect("a world config always serialises");
        // Tasks with layouts of their own move devices, part of the world: their cells count.
        for (i, t) in self.tasks.iter().enumerate() {
            if t.device_cells.is_some() || t.layout_seed.is_some() {
                let layout = (&t.device_cells, t.layout_seed);
                text.push_str(&format!("tasks[{i}] layout = {layout:?}\n"));
            }
        }
        let mut hasher = fnv::FnvHasher::default();
        std::hash::Hasher::write(&mut hasher, text.as_bytes());
        std::hash::Hasher::finish(&hasher)
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

    /// The meta-test tasks, each with its id (its index in `tasks`).
    pub fn meta_test_tasks(&self) -> impl Iterator<Item = (u32, &TaskConfig)> {
        (0u32..)
            .zip(&self.tasks)
            .filter(|(_, t)| t.role == TaskRole::MetaTest)
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
        self.tunnel.check_hosts(&self.tasks)?;
        self.tunnel.check_security()?;
        self.check_limits()?;
        self.check_power()?;
        self.planner.check_memory(&self.world)
    }

    /// Refuses a team (`world.uavs` > 1) where `what` flies one UAV so far: teams step, and are
    /// evaluated with the fixed policies, in `uavmeta env rollout` (docs/MODEL.md section 11).
    pub fn require_one_uav(&self, what: &str) -> Result<(), ConfigError> {
        let uavs = self.world.uavs;
        if uavs == 1 {
            return Ok(());
        }
        let expected = format!(
            "1: {what} flies one UAV so far; a team of UAVs runs in `uavmeta env rollout` with \
             random, stalest, greedy, planner, eps:P or actions:FILE (docs/MODEL.md section 11)"
        );
        Err(Broken::new("world.uavs", &uavs, expected).at(&self.origin))
    }

    /// What a launch needs beyond [`Config::validate`]: its fine-tuning shots fit in each task's
    /// dataset of `collect.transitions`. Only a launch reads `learner.shots`, so a `collect` or
    /// `train` of fewer transitions than the default's shots is not refused for it.
    pub fn validate_launch(&self) -> Result<(), ConfigError> {
        let (shots, transitions) = (self.learner.shots, self.collect.transitions);
        if shots <= transitions {
            return Ok(());
        }
        let expected = format!(
            "at most collect.transitions = {transitions} (the size of each task's dataset), \
             or 0 for all of it"
        );
        Err(Broken::new("learner.shots", &shots, expected).at(&self.origin))
    }

    /// Shots N of a launch's fine-tuning runs: `learner.shots`, or the whole dataset when it is 0.
    pub fn fine_tune_shots(&self) -> usize {
        match self.learner.shots {
            0 => self.collect.transitions,
            n => n,
        }
    }

    /// Every power the world can ask for, and the reward it weighs it into, is a finite number:
    /// a rate, a noise or a distance at the edge of f64 makes `inf`, which no learner reads.
    fn check_power(&self) -> Result<(), Broken> {
        let w = &self.world;
        let power = w.largest_power_mw();
        let lambda = self.tasks.iter().map(|t| t.lambda).fold(0.0, f64::max);
        if power.is_finite() && (lambda * power / w.devices as f64).is_finite() {
            return Ok(());
        }
        let expected = format!(
            "a world whose largest transmit power and reward are finite numbers; world.bits = \
             {:?}, world.bandwidth_hz = {:?}, world.noise_dbm = {:?}, world.g0_db = {:?}, \
             world.height_m = {:?}, world.cell_m = {:?}, world.grid_cells = {}, \
             world.rain_mm_per_h = {:?}, world.rain_phi = {:?}, world.rain_varphi = {:?} and the \
             largest tasks.lambda = {lambda:?} make it {power:?} mW",
            w.bits,
            w.bandwidth_hz,
            w.noise_dbm,
            w.g0_db,
            w.height_m,
            w.cell_m,
            w.grid_cells,
            w.rain_mm_per_h,
            w.rain_phi,
            w.rain_varphi
        );
        Err(Broken::new("world", &power, expected))
    }

    /// Every task has a name of its own, and a rain zone inside the grid.
    fn check_tasks(&self) -> Result<(), Broken> {
        for (i, t) in self.tasks.iter().enumerate() {
            if t.name.is_empty() || self.tasks[..i].iter().any(|o| o.name == t.name) {
                let expected = "a non-empty name no other task has";
                return Err(Broken::new(format!("tasks[{i}].name"), &t.name, expected));
            }
            t.check_rain(i, self.world.grid_cells)?;
            t.check_layout(i, &self.world)?;
        }
        Ok(())
    }
}

/// A value of the wrong type as one line naming its dotted key (`key `collect.dqn.steps` = -1:
/// invalid value: integer `-1`, expected usize`), found from where the parser stopped in the
/// file `text` (with any overrides merged in, so its line numbers would mislead).
fn type_error(text: &str, error: &toml::de::Error) -> String {
    let message = error.message().trim().replace('\n', " ");
    let Some(span) = error.span() else {
        return message;
    };
    match key_at(text, span.start) {
        Some((key, value)) => format!("key `{key}` = {value}: {message}"),
        None => message,
    }
}

/// The dotted key whose line holds byte `at` of `text` (`tasks[1].lambda` in an array of
/// tables), and the value that line gives it.
fn key_at(text: &str, at: usize) -> Option<(String, String)> {
    let before = text.get(..at)?;
    let line_start = before.rfind('\n').map_or(0, |i| i + 1);
    let line = text[line_start..].lines().next()?;
    let (name, value) = line.split_once('=')?;
    let (name, value) = (name.trim(), value.trim().to_string());
    let headers = before[..line_start].lines().map(str::trim);
    let Some(header) = headers.clone().rev().find(|l| l.starts_with('[')) else {
        return Some((name.to_string(), value));
    };
    if let Some(table) = header.strip_prefix("[[").and_then(|h| h.strip_suffix("]]")) {
        let index = headers.filter(|l| *l == header).count() - 1;
        return Some((format!("{table}[{index}].{name}"), value));
    }
    let table = header.trim_start_matches('[').trim_end_matches(']');
    Some((format!("{table}.{name}"), value))
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
// (`uavmeta_runtime::launch::resources`); these caps keep every estimate far from overflow and a
// typo (a batch of 10 000 000) from reaching any process. A cap on one field is a rule of its
// section (`run.transitions_per_message`, `world.devices`, ...); the caps here span sections.

/// Most tasks in `[[tasks]]`: each has a dataset file, services and actors of its own.
pub const MAX_TASKS: usize = 64;
/// Most actors of a run on one host, tasks x `collect.actors_per_task`.
pub const MAX_ACTORS: usize = 256;
/// Most entries of a world's power table, grid_cells^2 x K: two tables of 8 bytes an entry,
/// 256 MiB, in every process that builds the world.
pub const MAX_POWER_TABLE: u64 = 1 << 24;

impl Config {
    /// The resource caps above.
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
