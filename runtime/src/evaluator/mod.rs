//! The evaluator process (`uavmeta evaluator --run R`): scores every announced checkpoint on its
//! task's true environment and exports the figures.
//!
//! For each `CheckpointReady` it loads the checkpoint, runs the greedy policy for
//! `learner.eval_episodes` Monte-Carlo episodes seeded `learner.eval_seed` (the same episodes for
//! every method and epoch, [`Evaluator`]), sets the per-task, per-method gauges and appends one
//! row to the run's `evaluations.csv` for plots.
//!
//! **Restart.** An evaluator (re)started mid-run or after the meta-learner has exited first queues
//! every complete checkpoint already in the run directory, in the order the meta-learner announces
//! them, then listens. Each checkpoint is evaluated once: those its CSV already holds, and
//! announcements (the history included) of checkpoints it has queued, are skipped. A shutdown
//! announcement makes it finish the checkpoints it knows of, then exit.

use std::collections::{BTreeSet, VecDeque};
use std::fs::{File, OpenOptions};
use std::io::{BufRead, BufReader, Write};
use std::path::Path;
use std::time::{Duration, Instant};

use uavmeta_actors::policy::q_policy::Evaluator;
use uavmeta_learner::checkpoint::{self, CheckpointError};
use uavmeta_learner::train::EvaluatePolicy;
use uavmeta_proto::config::Config;
use uavmeta_proto::method::Method;
use uavmeta_proto::payload::{CheckpointReady, SCHEMA_VERSION};
use uavmeta_proto::stats::PolicyMetrics;

use crate::liveness;
use crate::metrics::MetricsError;
use crate::process::Process;
use crate::run_dir::RunDir;
use crate::transport::{self, TransportError};
use uavmeta_proto::fs::FileError;

mod metrics;

/// The evaluator's process name: node, port file and metrics snapshot.
pub const PROCESS: &str = "evaluator";

/// How long the loop sleeps between looks for announcements.
const POLL: Duration = Duration::from_millis(50);

#[derive(Debug, thiserror::Error)]
pub enum EvaluatorError {
    #[error(transparent)]
    Transport(#[from] TransportError),
    #[error(transparent)]
    Metrics(#[from] MetricsError),
    #[error(transparent)]
    Checkpoint(#[from] CheckpointError),
    #[error(transparent)]
    File(#[from] FileError),
}

/// One evaluated checkpoint: a row of `evaluations.csv`. Power is in milliwatts, as in every
/// table and CSV; the metrics keep watts (base units).
#[derive(Debug, Clone, PartialEq)]
pub struct EvaluationRow {
    pub task: String,
    pub method: String,
    pub epoch: u32,
    pub policy: PolicyMetrics,
}

const CSV_HEADER: &str = "task,method,epoch,episodes,return,return_ci95,aoi,aoi_ci95,power_mw,power_mw_ci95,outages,outages_ci95";

impl EvaluationRow {
    /// The row of `method` (a [`Method`]'s name, or a heuristic's) on `task` after `epoch`.
    pub fn new(task: &str, method: &str, epoch: u32, m: &PolicyMetrics) -> Self {
        Self {
            task: task.to_string(),
            method: method.to_string(),
            epoch,
            policy: *m,
        }
    }

    fn to_csv(&self) -> String {
        let (task, method, epoch) = (&self.task, &self.method, self.epoch);
        let (episodes, cells) = (self.policy.episodes, self.policy.csv());
        format!("{task},{method},{epoch},{episodes},{cells}")
    }

    fn parse(line: &str) -> Option<Self> {
        let f: Vec<&str> = line.split(',').collect();
        if f.len() != 12 {
            return None;
        }
        Some(Self {
            task: f[0].to_string(),
            method: f[1].to_string(),
            epoch: f[2].parse().ok()?,
            policy: PolicyMetrics::parse_csv(&f[4..], f[3].parse().ok()?)?,
        })
    }
}

/// Every row of an evaluations CSV; a torn last line (a crash mid-write) is skipped.
pub fn read_rows(path: &Path) -> std::io::Result<Vec<EvaluationRow>> {
    let file = std::fs::File::open(path)?;
    let mut rows = Vec::new();
    for line in BufReader::new(file).lines() {
        let line = line?;
        if line == CSV_HEADER {
            continue;
        }
        if let Some(row) = EvaluationRow::parse(&line) {
            rows.push(row);
        }
    }
    Ok(rows)
}

/// Runs the evaluator of `run` until a shutdown (after finishing what was announced) or
/// SIGINT/SIGTERM. Returns the checkpoints evaluated.
pub fn run(run: &RunDir, config: &Config) -> Result<u64, EvaluatorError> {
    let process = Process::start(run, config, PROCESS)?;
    let metrics = metrics::EvaluatorMetrics::new();
    let _server = process.serve_metrics(run, config, metrics.registry.clone())?;
    let announcements = transport::control_subscriber(&transport::checkpoint_ready_service(
        &process.node,
        &process.names,
        config,
    )?)?;

    let csv_path = run.evaluations_csv();
    let (mut csv, mut done) = open_csv(&csv_path)?;

    let mut queue: VecDeque<CheckpointReady> = checkpoints_on_disk(run, config).into();
    if !queue.is_empty() {
        tracing::info!(
            checkpoints = queue.len(),
            "found checkpoints in the run directory"
        );
    }
    let mut stopping = false;
    let mut evaluated = 0u64;
    while liveness::keep_running(
        &process.node,
        if queue.is_empty() {
            POLL
        } else {
            Duration::ZERO
        },
    ) {
        while let Some(m) = announcements.receive().map_err(transport::receive_failed(
            "receive a checkpoint announcement",
        ))? {
            if m.schema_version == SCHEMA_VERSION {
                queue.push_back(*m);
            }
        }
        stopping |= transport::shutdown_requested(&process.shutdown)?;
        let Some(next) = queue.pop_front() else {
            if stopping {
                break;
            }
            continue;
        };
        let (Some(method), Some(task)) = (
            Method::from_code(next.method),
            config.tasks.get(next.task as usize),
        ) else {
            tracing::warn!(
                method = next.method,
                task = next.task,
                "ignored an announcement of an unknown method or task"
            );
            continue;
        };
        if !done.insert((task.name.clone(), method.name(), next.epoch)) {
            continue;
        }
        let start = Instant::now();
        let path = run.checkpoint(method, task, next.epoch);
        let (q, _) = checkpoint::load(&path, config)?;
        let result = Evaluator::from_config(config, task).evaluate(&q);
        let row = EvaluationRow::new(&task.name, &method.name(), next.epoch, &result);
        writeln!(csv, "{}", row.to_csv()).map_err(FileError::at(&csv_path, "append a row"))?;
        csv.flush().map_err(FileError::at(&csv_path, "flush"))?;
        metrics.observe(&row, start.elapsed());
        evaluated += 1;
        tracing::info!(task = %task.name, %method, epoch = next.epoch, ret = row.policy.ret.mean, aoi = row.policy.aoi.mean, power_mw = row.policy.power_mw.mean, outages = row.policy.outages.mean, "evaluated");
    }
    Ok(evaluated)
}

/// The (task, method, epoch) of evaluated checkpoints.
type Evaluated = BTreeSet<(String, String, u32)>;

/// The evaluations CSV at `path`, opened for appending (with its header when new), and the
/// checkpoints its rows already hold. An error says what failed.
fn open_csv(path: &Path) -> Result<(File, Evaluated), FileError> {
    let mut done = BTreeSet::new();
    if path.exists() {
        for row in read_rows(path).map_err(FileError::at(path, "read"))? {
            done.insert((row.task, row.method, row.epoch));
        }
    }
    let fresh = !path.exists();
    let mut csv = OpenOptions::new()
        .create(true)
        .append(true)
        .open(path)
        .map_err(FileError::at(path, "open"))?;
    if fresh {
        writeln!(csv, "{CSV_HEADER}").map_err(FileError::at(path, "write"))?;
    }
    Ok((csv, done))
}

/// The complete checkpoints in `run`'s directory, as the meta-learner announces them: every w0
/// checkpoint for each meta-test task, then each meta-test task's online DQN agent, the context
/// learner's zero-shot policy and the epochs of its fine-tuned methods.
fn checkpoints_on_disk(run: &RunDir, config: &Config) -> Vec<CheckpointReady> {
    let test_tasks: Vec<_> = config.meta_test_tasks().collect();
    let complete =
        |method, task, epoch| checkpoint::read_meta(&run.checkpoint(method, task, epoch)).is_ok();
    let mut found = Vec::new();
    for epoch in 1..=config.meta.meta_epochs as u32 {
        for &(id, task) in &test_tasks {
            if complete(Method::MetaInit, task, epoch) {
                found.push(CheckpointReady::new(Method::MetaInit, id, epoch));
            }
        }
    }
    for &(id, task) in &test_tasks {
        for method in [Method::OnlineDqn, Method::ContextInit] {
            if complete(method, task, 1) {
                found.push(CheckpointReady::new(method, id, 1));
            }
        }
        for method in Method::fine_tuned(config.meta.inner_loss, &config.learner.baselines) {
            for epoch in 1..=config.learner.epochs as u32 {
                if complete(method, task, epoch) {
                    found.push(CheckpointReady::new(method, id, epoch));
                }
            }
        }
    }
    found
}

#[cfg(test)]
mod tests {
    use uavmeta_proto::stats::Estimate;

    use super::*;

    #[test]
    fn rows_round_trip_and_torn_lines_are_skipped() {
        let estimate = |mean, ci95| Estimate { mean, ci95 };
        let policy = PolicyMetrics {
            episodes: 10,
            ret: estimate(-1234.5, 12.0),
            aoi: estimate(6.25, 0.5),
            power_mw: estimate(1.6, 0.1),
            outages: estimate(0.0, 0.0),
        };
        let row = EvaluationRow::new("lambda-300", "cql-maml", 7, &policy);
        let line = "lambda-300,cql-maml,7,10,-1234.5,12,6.25,0.5,1.6,0.1,0,0";
        assert_eq!(row.to_csv(), line);
        let dir = tempfile::tempdir().expect("temp dir");
        let path = dir.path().join("e.csv");
        std::fs::write(
            &path,
            format!("{CSV_HEADER}\n{}\nlambda-300,cql,3,10,-12", row.to_csv()),
        )
        .expect("write");
        assert_eq!(read_rows(&path).expect("read"), vec![row]);
    }
}
