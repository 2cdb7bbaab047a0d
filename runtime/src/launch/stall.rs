//! Datasets that stop growing (issue #61). A task's dataset can stay short for ever while every
//! process is alive and beating: the store may drop what the task's actors send (as duplicates,
//! when another publisher sent under an actor's id numbers ahead of it), and the actors, having
//! sent everything, wait. The heartbeat cannot see this, so a watch on a thread of its own reads
//! the store's and the task's actors' /metrics every [`LOOK_EVERY`], and reports a task whose
//! dataset has not grown for `run.hang_timeout_seconds` while its actors made progress: they
//! published more, or have sent everything (phase `sent`). The launcher then ends the run with an
//! error naming the task, its actors and what the store did with their transitions.

use std::sync::mpsc;
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use uavmeta_proto::config::Config;
use uavmeta_proto::metrics::{actor as actor_metrics, store as store_metrics};

use crate::actor::Phase;
use crate::metrics::{scrape_process, sum, Sample};
use crate::run_dir::RunDir;
use crate::store;

/// How often the watch reads the metrics.
pub(super) const LOOK_EVERY: Duration = Duration::from_secs(1);

/// A task whose dataset stopped growing while its actors went on.
#[derive(Debug, Clone, PartialEq)]
pub struct Stall {
    pub task: String,
    pub stored: f64,
    pub target: usize,
    pub seconds: f64,
    /// Each actor of the task: its name, phase and transitions published.
    pub actors: String,
    /// What the store did with the task's transitions.
    pub cause: String,
}

/// The watch's thread; it sends at most one [`Stall`].
pub(super) struct StallWatch {
    pub(super) stalled: mpsc::Receiver<Stall>,
    _stop: mpsc::Sender<()>,
    _thread: JoinHandle<()>,
}

impl StallWatch {
    /// Watches the tasks of `config`, whose local actors are `actors` (process name, task);
    /// `None` when `run.hang_timeout_seconds` is 0 (never).
    pub(super) fn start(
        run: &RunDir,
        config: &Config,
        actors: Vec<(String, String)>,
    ) -> Option<Self> {
        let timeout = Duration::from_secs_f64(config.run.hang_timeout_seconds);
        if timeout.is_zero() {
            return None;
        }
        let tasks = (config.tasks.iter())
            .map(|t| Progress::new(&t.name, &actors))
            .collect();
        let mut watch = Watch {
            run: run.clone(),
            host: config.run.metrics_host.clone(),
            target: config.collect.transitions,
            timeout,
            tasks,
        };
        let (stop, stopped) = mpsc::channel::<()>();
        let (found, stalled) = mpsc::channel();
        let thread = std::thread::Builder::new()
            .name("stall-watch".into())
            .spawn(move || {
                while let Err(mpsc::RecvTimeoutError::Timeout) = stopped.recv_timeout(LOOK_EVERY) {
                    if let Some(stall) = watch.look() {
                        let _ = found.send(stall);
                        return;
                    }
                }
            })
            .expect("a thread starts");
        Some(Self {
            stalled,
            _stop: stop,
            _thread: thread,
        })
    }
}

/// What the watch knows of one task.
struct Progress {
    task: String,
    actors: Vec<String>,
    /// The dataset's size when it last grew, and when.
    stored: f64,
    since: Instant,
    /// What the task's actors had published then.
    published: f64,
}

impl Progress {
    fn new(task: &str, actors: &[(String, String)]) -> Self {
        Self {
            task: task.to_string(),
            actors: (actors.iter())
                .filter(|(_, t)| t == task)
                .map(|(name, _)| name.clone())
                .collect(),
            stored: 0.0,
            since: Instant::now(),
            published: 0.0,
        }
    }
}

struct Watch {
    run: RunDir,
    host: String,
    target: usize,
    timeout: Duration,
    tasks: Vec<Progress>,
}

impl Watch {
    /// One look at every task; the first that stalled, if any.
    fn look(&mut self) -> Option<Stall> {
        let Some(store) = scrape_process(&self.run, &self.host, store::PROCESS) else {
            // No store to ask (it restarts): the heartbeat watches it, not this.
            self.tasks.iter_mut().for_each(|t| t.since = Instant::now());
            return None;
        };
        let mut tasks = std::mem::take(&mut self.tasks);
        let stall = tasks.iter_mut().find_map(|t| self.look_at(t, &store));
        self.tasks = tasks;
        stall
    }

    fn look_at(&self, progress: &mut Progress, store: &[Sample]) -> Option<Stall> {
        let task = [("task", progress.task.as_str())];
        if sum(store, store_metrics::DATASET_READY, &task) > 0.0 {
            return None;
        }
        let stored = sum(store, store_metrics::DATASET_TRANSITIONS, &task);
        let actors: Vec<(&String, Option<Vec<Sample>>)> = (progress.actors.iter())
            .map(|name| (name, self.actor_samples(name)))
            .collect();
        let published: f64 = (actors.iter())
            .filter_map(|(_, s)| s.as_deref())
            .map(|s| sum(s, actor_metrics::TRANSITIONS_PUBLISHED, &[]))
            .sum();
        let all_sent = actors.iter().any(|(_, s)| s.as_deref().is_some_and(sent));
        let went_on = all_sent || published > progress.published;
        if stored > progress.stored || !went_on {
            (progress.stored, progress.published) = (stored, published);
            progress.since = Instant::now();
            return None;
        }
        let still = progress.since.elapsed();
        (still >= self.timeout).then(|| Stall {
            task: progress.task.clone(),
            stored,
            target: self.target,
            seconds: still.as_secs_f64(),
            actors: describe_actors(&actors),
            cause: cause(store, &progress.task),
        })
    }

    /// An actor's samples: live from its /metrics, else from the snapshot it left on exit.
    fn actor_samples(&self, name: &str) -> Option<Vec<Sample>> {
        scrape_process(&self.run, &self.host, name).or_else(|| {
            let text = std::fs::read_to_string(self.run.metrics_snapshot(name)).ok()?;
            crate::metrics::parse(&text).ok()
        })
    }
}

/// Whether an actor reports that it has sent everything it has.
fn sent(samples: &[Sample]) -> bool {
    sum(
        samples,
        actor_metrics::PHASE,
        &[("phase", Phase::Sent.name())],
    ) > 0.0
}

fn describe_actors(actors: &[(&String, Option<Vec<Sample>>)]) -> String {
    let one = |(name, samples): &(&String, Option<Vec<Sample>>)| match samples {
        None => format!("{name} (no metrics)"),
        Some(s) => {
            let phase = Phase::ALL
                .into_iter()
                .find(|p| sum(s, actor_metrics::PHASE, &[("phase", p.name())]) > 0.0)
                .map_or("unknown", Phase::name);
            let published = sum(s, actor_metrics::TRANSITIONS_PUBLISHED, &[]);
            let unacknowledged = sum(s, actor_metrics::TRANSITIONS_UNACKNOWLEDGED, &[]);
            format!(
                "{name} (phase {phase}, {published} published, {unacknowledged} unacknowledged)"
            )
        }
    };
    actors.iter().map(one).collect::<Vec<_>>().join(", ")
}

/// What the store did with the task's transitions, and what that suggests.
fn cause(store: &[Sample], task: &str) -> String {
    let dropped = |reason| {
        let labels = [("task", task), ("reason", reason)];
        sum(store, store_metrics::TRANSITIONS_DROPPED, &labels)
    };
    let duplicates = dropped(store_metrics::DUPLICATE);
    let missing = sum(store, store_metrics::TRANSITIONS_MISSING, &[("task", task)]);
    let counts = format!(
        "the store dropped {duplicates} of the task's transitions as duplicates, {} as invalid \
         and {} as foreign, and counts {missing} missing",
        dropped(store_metrics::INVALID),
        dropped(store_metrics::FOREIGN),
    );
    match duplicates > 0.0 && missing > 0.0 {
        true => format!(
            "{counts}: another publisher has sent under an actor's id, numbered ahead of it, so \
             the store takes that actor's own transitions for duplicates (the store's log names \
             the gap)"
        ),
        false => counts,
    }
}
