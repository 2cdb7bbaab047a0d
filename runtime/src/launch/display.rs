//! What `uavmeta launch` draws on a terminal while the run goes: one row per actor (its phase,
//! then its progress: the online DQN agent's steps, exploration rate and recent return while it
//! trains, then the transitions it sent), the meta-learner (waiting for the datasets, meta-epoch
//! and meta-loss, then the meta-test's fine-tuning epochs), and per meta-test task the
//! evaluator's latest return of every method.
//!
//! Everything comes from what the processes publish: their /metrics (the actors', the
//! meta-learner's, the store's) and the evaluator's CSV, read twice a second on a thread of its
//! own, so that a slow or stopped child never delays the supervisor. Rows are redrawn in place;
//! log lines must go through the same [`MultiProgress`] (`suspend`), since a line written
//! between its rows shifts them, and the next redraw then leaves the top rows behind, drawn
//! twice. When the run ends the rows are cleared, so only the results table stays.

use std::sync::mpsc::{self, RecvTimeoutError};
use std::thread::JoinHandle;
use std::time::Duration;

use indicatif::{MultiProgress, ProgressBar, ProgressStyle};
use uavmeta_proto::config::{Config, TaskRole};
use uavmeta_proto::method::Method;
use uavmeta_proto::metrics::{self, Metric};

use crate::actor::Phase;
use crate::metrics::{scrape_process, sum, Sample};
use crate::run_dir::RunDir;
use crate::{meta_learner, store};

/// How often the rows are refreshed.
const REFRESH: Duration = Duration::from_millis(500);

/// The rows, refreshed on their own thread until [`Display::finish`].
pub(super) struct Display {
    stop: mpsc::Sender<()>,
    thread: JoinHandle<View>,
}

impl Display {
    /// Draws the rows of `config`'s run on `terminal`; `actors` are the actors' process names
    /// and tasks, in the order of their rows.
    pub(super) fn start(
        terminal: &MultiProgress,
        run: &RunDir,
        config: &Config,
        actors: Vec<(String, String)>,
    ) -> Self {
        let view = View::new(terminal, run, config, actors);
        let (stop, stopped) = mpsc::channel();
        let thread = std::thread::Builder::new()
            .name("display".into())
            .spawn(move || view.run(&stopped))
            .expect("a thread starts");
        Self { stop, thread }
    }

    /// Stops refreshing and erases the rows.
    pub(super) fn finish(self) {
        drop(self.stop);
        if let Ok(view) = self.thread.join() {
            for row in view.rows() {
                row.finish_and_clear();
            }
        }
    }
}

struct ActorRow {
    process: String,
    task: String,
    bar: ProgressBar,
}

/// The rows and what they are drawn from.
struct View {
    run: RunDir,
    host: String,
    dqn_steps: u64,
    transitions: u64,
    meta_epochs: u64,
    fine_tune_epochs: u64,
    tasks: Vec<String>,
    /// Tasks whose dataset the store reported complete; kept when the store restarts.
    stored: Vec<bool>,
    actors: Vec<ActorRow>,
    meta: ProgressBar,
    /// Per meta-test task: its name and row.
    evaluations: Vec<(String, ProgressBar)>,
}

impl View {
    fn new(
        terminal: &MultiProgress,
        run: &RunDir,
        config: &Config,
        actors: Vec<(String, String)>,
    ) -> Self {
        let bar = ProgressStyle::with_template("{prefix:>16} [{bar:30}] {wide_msg}")
            .expect("valid template")
            .progress_chars("=> ");
        let text = ProgressStyle::with_template("{prefix:>16} {wide_msg}").expect("valid template");
        let row = |prefix: String, style: &ProgressStyle, message: &'static str| {
            let row = terminal.add(ProgressBar::new(1).with_style(style.clone()));
            row.set_prefix(prefix);
            row.set_message(message);
            row
        };
        let per_task = config.collect.actors_per_task;
        let actors = actors
            .into_iter()
            .enumerate()
            .map(|(i, (process, task))| {
                let prefix = match per_task {
                    1 => task.clone(),
                    _ => format!("{task} #{}", i % per_task + 1),
                };
                let bar = row(prefix, &bar, "starting");
                ActorRow { process, task, bar }
            })
            .collect();
        let meta = row(
            meta_learner::PROCESS.into(),
            &bar,
            "waiting for the datasets",
        );
        let test_tasks = config.tasks_with_role(TaskRole::MetaTest);
        let evaluations = test_tasks
            .map(|t| {
                let waiting = "waiting for the first checkpoint";
                (t.name.clone(), row("evaluator".into(), &text, waiting))
            })
            .collect();
        let test_count = config.tasks_with_role(TaskRole::MetaTest).count();
        let methods = Method::fine_tuned(config.meta.inner_loss, &config.learner.baselines).len();
        Self {
            run: run.clone(),
            host: config.run.metrics_host.clone(),
            dqn_steps: config.collect.dqn.steps as u64,
            transitions: config.collect.transitions as u64,
            meta_epochs: config.meta.meta_epochs as u64,
            fine_tune_epochs: (test_count * methods * config.learner.epochs) as u64,
            tasks: config.tasks.iter().map(|t| t.name.clone()).collect(),
            stored: vec![false; config.tasks.len()],
            actors,
            meta,
            evaluations,
        }
    }

    fn rows(&self) -> impl Iterator<Item = &ProgressBar> {
        let actors = self.actors.iter().map(|a| &a.bar);
        actors
            .chain([&self.meta])
            .chain(self.evaluations.iter().map(|(_, row)| row))
    }

    /// Refreshes every [`REFRESH`] until `stop` is dropped; returns the view to be cleared.
    fn run(mut self, stop: &mpsc::Receiver<()>) -> Self {
        loop {
            self.refresh();
            match stop.recv_timeout(REFRESH) {
                Err(RecvTimeoutError::Timeout) => continue,
                _ => return self,
            }
        }
    }

    fn refresh(&mut self) {
        if let Some(store) = self.scrape(store::PROCESS) {
            for (task, stored) in self.tasks.iter().zip(&mut self.stored) {
                let ready = [("task", task.as_str())];
                *stored |= sum(&store, metrics::store::DATASET_READY, &ready) > 0.0;
            }
        }
        for row in &self.actors {
            let task = self.tasks.iter().position(|t| *t == row.task);
            if task.is_some_and(|i| self.stored[i]) {
                row.bar.set_length(self.transitions);
                row.bar.set_position(self.transitions);
                row.bar.set_message(format!(
                    "stored: the dataset holds its {} transitions",
                    self.transitions
                ));
            } else if let Some(samples) = self.scrape(&row.process) {
                self.show_actor(&row.bar, &samples);
            }
        }
        if let Some(samples) = self.scrape(meta_learner::PROCESS) {
            self.show_meta_learner(&samples);
        }
        self.show_evaluations();
    }

    /// A live process's samples, through the port it published; `None` while it has none.
    fn scrape(&self, process: &str) -> Option<Vec<Sample>> {
        scrape_process(&self.run, &self.host, process)
    }

    fn show_actor(&self, bar: &ProgressBar, samples: &[Sample]) {
        let value = |metric: Metric| sum(samples, metric, &[]);
        let phase = Phase::ALL
            .into_iter()
            .find(|p| sum(samples, metrics::actor::PHASE, &[("phase", p.name())]) > 0.0);
        let Some(phase) = phase else { return };
        if phase == Phase::Training {
            let steps = value(metrics::actor::STEPS) as u64;
            let ret = value(metrics::actor::ONLINE_DQN_RECENT_RETURN);
            let ret = match ret.is_nan() {
                true => "none yet".to_string(),
                false => format!("{ret:.1}"),
            };
            bar.set_length(self.dqn_steps);
            bar.set_position(steps);
            bar.set_message(format!(
                "training online DQN: step {steps}/{}, epsilon {:.2}, return {ret} (last {} episodes)",
                self.dqn_steps,
                value(metrics::actor::ONLINE_DQN_EPSILON),
                uavmeta_actors::policy::dqn_online::RECENT_EPISODES,
            ));
            return;
        }
        let sent = (value(metrics::actor::TRANSITIONS_PUBLISHED) as u64).min(self.transitions);
        bar.set_length(self.transitions);
        bar.set_position(sent);
        bar.set_message(match phase {
            Phase::Sent => format!(
                "sent {sent}/{} transitions; waiting for the store",
                self.transitions
            ),
            _ => format!("sending transitions: {sent}/{}", self.transitions),
        });
    }

    fn show_meta_learner(&self, samples: &[Sample]) {
        let value = |metric: Metric| sum(samples, metric, &[]);
        let fine_tuned = value(metrics::meta_learner::FINE_TUNE_EPOCHS) as u64;
        let epoch = value(metrics::meta_learner::META_EPOCH) as u64;
        let (length, position, message) = if fine_tuned > 0 {
            let all = self.fine_tune_epochs;
            (
                all,
                fine_tuned,
                format!("meta-test: {fine_tuned}/{all} fine-tuning epochs"),
            )
        } else if epoch > 0 {
            let loss = value(metrics::meta_learner::META_LOSS);
            let all = self.meta_epochs;
            (
                all,
                epoch,
                format!("meta-train: meta-epoch {epoch}/{all}, meta-loss {loss:.4}"),
            )
        } else {
            let stored = self.stored.iter().filter(|s| **s).count();
            let all = self.stored.len();
            (
                all as u64,
                stored as u64,
                format!("waiting for the datasets: {stored}/{all} stored"),
            )
        };
        self.meta.set_length(length);
        self.meta.set_position(position);
        self.meta.set_message(message);
    }

    /// The latest return of every method on each meta-test task, in the results table's order.
    fn show_evaluations(&self) {
        let Ok(mut rows) = super::report::latest_results(&self.run) else {
            return;
        };
        rows.sort_by_key(|r| super::report::row_rank(&r.method));
        for (task, bar) in &self.evaluations {
            let returns: Vec<String> = rows
                .iter()
                .filter(|r| r.task == *task)
                .map(|r| match super::report::is_reference(&r.method) {
                    true => format!("{} {:.1}", r.method, r.policy.ret.mean),
                    false => format!("{}@{} {:.1}", r.method, r.epoch, r.policy.ret.mean),
                })
                .collect();
            if !returns.is_empty() {
                bar.set_message(format!("{task} returns: {}", returns.join(" | ")));
            }
        }
    }
}
