//! What `uavmeta dataset inspect` prints: a dataset file's header, its task, what its
//! transitions cover, reward and return statistics, and how often each action was taken.
//!
//! The file is read by `DatasetReader::open`, which checks every CRC32, so a summary exists only
//! for an undamaged file. With the run's config, every transition is also checked as the store
//! checks what it appends (`uavmeta_world::validate`): a file that fails is named with each
//! failing check, and `uavmeta dataset inspect` exits with an error.

use std::collections::BTreeSet;
use std::fmt;
use std::path::PathBuf;

use uavmeta_proto::config::{Config, TaskConfig, MOVES};
use uavmeta_proto::dataset::{DatasetHeader, DatasetReader, LEARNER_HOST, SCHEMA_VERSION};
use uavmeta_proto::fs::FileError;
use uavmeta_proto::stats::Estimate;
use uavmeta_world::validate::{Rejection, Validator};

use crate::{runs, InteropError};

/// One dataset file, summarised.
#[derive(Debug, Clone)]
pub struct Summary {
    pub path: PathBuf,
    pub bytes: u64,
    /// Chunks, each checked against its CRC32.
    pub chunks: usize,
    pub header: DatasetHeader,
    /// The task as the config defines it, with the config's origin, when one was given.
    pub task: Option<(TaskConfig, String)>,
    pub transitions: usize,
    /// Transitions per host that made them: its name, `LEARNER_HOST` for the learner's own.
    pub hosts: Vec<(String, u64)>,
    pub actors: usize,
    /// Distinct (actor, episode) pairs with at least one step in the file.
    pub episodes: usize,
    /// Runs of consecutive steps ([`runs::split`]).
    pub runs: usize,
    /// Returns of the runs that are whole episodes, from the first step to the time limit.
    pub episode_returns: Vec<f64>,
    pub rewards: Vec<f64>,
    /// Transitions per action index, `move * K + device`.
    pub actions: Vec<u64>,
    /// With a config: the checks the store makes, run on every transition.
    pub validation: Option<Validation>,
}

/// What the store's checks found in a file.
#[derive(Debug, Clone, Default)]
pub struct Validation {
    /// Transitions that fail a check, per check (the `reason` label's values), in check order.
    pub failed: Vec<(&'static str, u64)>,
    /// The first failure, with its transition's index in the file.
    pub first: Option<(usize, Rejection)>,
}

impl Validation {
    /// Checks every transition against `task`'s world.
    fn run(
        config: &Config,
        task: &TaskConfig,
        transitions: &[uavmeta_proto::dataset::Transition],
    ) -> Self {
        let mut validator = Validator::new(&config.world, task);
        let mut found = Self::default();
        for (index, t) in transitions.iter().enumerate() {
            let Err(rejection) = validator.check(t.into()) else {
                continue;
            };
            match found
                .failed
                .iter_mut()
                .find(|(r, _)| *r == rejection.reason)
            {
                Some((_, count)) => *count += 1,
                None => found.failed.push((rejection.reason, 1)),
            }
            found.first.get_or_insert((index, rejection));
        }
        found
    }

    /// Transitions that fail any check.
    pub fn failures(&self) -> u64 {
        self.failed.iter().map(|(_, n)| n).sum()
    }
}

impl Summary {
    /// Summarises the file `reader` read; with a `config`, checks that the file comes from its
    /// world and names the task's lambda and rain.
    pub fn new(reader: &DatasetReader, config: Option<&Config>) -> Result<Self, InteropError> {
        let header = reader.header().clone();
        let task = match config {
            Some(config) => {
                reader.check_world(config)?;
                let task = config.task(&header.task_name)?.clone();
                Some((task, config.origin.clone()))
            }
            None => None,
        };
        let path = reader.path().to_path_buf();
        let bytes = std::fs::metadata(&path)
            .map_err(FileError::at(&path, "stat"))?
            .len();
        let transitions = reader.transitions();
        let mut actions = vec![0; header.layout().action_count()];
        for t in transitions {
            actions[usize::from(t.action)] += 1;
        }
        let runs = runs::split(Vec::from(transitions));
        let validation = task
            .as_ref()
            .zip(config)
            .map(|((task, _), config)| Validation::run(config, task, transitions));
        Ok(Self {
            validation,
            path,
            bytes,
            chunks: reader.chunks(),
            transitions: transitions.len(),
            hosts: (reader.provenance().into_iter())
                .map(|(host, n)| (host.to_string(), n))
                .collect(),
            actors: distinct(reader.with_hosts().map(|(h, t)| (h, t.actor))),
            episodes: distinct(reader.with_hosts().map(|(h, t)| (h, t.actor, t.episode))),
            runs: runs.len(),
            episode_returns: runs
                .iter()
                .filter(|run| runs::is_episode(run))
                .map(|run| run.iter().map(|t| f64::from(t.reward)).sum())
                .collect(),
            rewards: transitions.iter().map(|t| f64::from(t.reward)).collect(),
            actions,
            header,
            task,
        })
    }

    fn write_task(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let h = &self.header;
        write!(
            f,
            "task         `{}`, index {} in [[tasks]]",
            h.task_name, h.task
        )?;
        match &self.task {
            Some((task, origin)) => {
                let rain = match task.rain {
                    Some(r) => format!("rain over cells ({}, {})-({}, {})", r.x0, r.y0, r.x1, r.y1),
                    None => "no rain".into(),
                };
                writeln!(f, ": lambda = {}, {rain} (from {origin})", task.lambda)
            }
            None => writeln!(f, " (lambda and rain: give the config with --config)"),
        }
    }

    fn write_statistics(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let (min, max) = range(&self.rewards);
        writeln!(
            f,
            "rewards      per step: mean {:.2} (95% CI), min {min:.2}, max {max:.2}",
            Estimate::from_samples(self.rewards.iter().copied())
        )?;
        if self.episode_returns.is_empty() {
            return writeln!(
                f,
                "returns      no whole episode (the file holds sampled steps, as from a replay buffer)"
            );
        }
        let (min, max) = range(&self.episode_returns);
        writeln!(
            f,
            "returns      {} whole episodes: mean {:.2} (95% CI), min {min:.2}, max {max:.2}",
            self.episode_returns.len(),
            Estimate::from_samples(self.episode_returns.iter().copied())
        )
    }

    /// The action histogram as a table: a row per move, a column per device.
    fn write_actions(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let devices = usize::from(self.header.devices);
        write!(f, "actions      {:<8}", "device")?;
        for device in 0..devices {
            write!(f, "{device:>6}")?;
        }
        writeln!(f, "{:>8}", "total")?;
        for (mv, counts) in MOVES.iter().zip(self.actions.chunks(devices)) {
            write!(f, "             {mv:<8}")?;
            for count in counts {
                write!(f, "{count:>6}")?;
            }
            writeln!(f, "{:>8}", counts.iter().sum::<u64>())?;
        }
        Ok(())
    }
}

impl fmt::Display for Summary {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let h = &self.header;
        writeln!(
            f,
            "{}: uavmeta dataset, schema version {SCHEMA_VERSION}, {} bytes in {} chunks, every CRC32 valid",
            self.path.display(),
            self.bytes,
            self.chunks
        )?;
        self.write_task(f)?;
        writeln!(
            f,
            "world        K = {} devices: observations of {} values, {} actions; world hash {:#018x}",
            h.devices,
            h.layout().observation_len(),
            h.layout().action_count(),
            h.world_hash
        )?;
        writeln!(
            f,
            "transitions  {} (actors: {}, episodes: {}) in {} runs of consecutive steps, {} of them whole episodes",
            self.transitions,
            self.actors,
            self.episodes,
            self.runs,
            self.episode_returns.len()
        )?;
        let hosts: Vec<String> = (self.hosts.iter())
            .map(|(host, n)| match host.as_str() {
                LEARNER_HOST => format!("learner host {n}"),
                remote => format!("{remote} {n}"),
            })
            .collect();
        writeln!(f, "made by      {}", hosts.join(", "))?;
        self.write_statistics(f)?;
        self.write_actions(f)?;
        self.write_validation(f)
    }
}

impl Summary {
    fn write_validation(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let Some(v) = &self.validation else {
            return writeln!(
                f,
                "checks       not run: give the run's config with --config"
            );
        };
        if v.failed.is_empty() {
            return writeln!(
                f,
                "checks       every transition passes the store's checks (uavmeta_world::validate)"
            );
        }
        let counts: Vec<String> = v.failed.iter().map(|(r, n)| format!("{r}: {n}")).collect();
        writeln!(
            f,
            "checks       {} transitions FAIL the store's checks ({})",
            v.failures(),
            counts.join(", ")
        )?;
        if let Some((index, rejection)) = &v.first {
            writeln!(f, "             first: transition {index}: {rejection}")?;
        }
        Ok(())
    }
}

fn distinct<T: Ord>(items: impl Iterator<Item = T>) -> usize {
    items.collect::<BTreeSet<T>>().len()
}

/// The smallest and largest of `values`, NaN for none.
fn range(values: &[f64]) -> (f64, f64) {
    values
        .iter()
        .fold((f64::NAN, f64::NAN), |(lo, hi), &v| (lo.min(v), hi.max(v)))
}
