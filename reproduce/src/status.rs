//! Where a plan in `OUT` stands, whichever engine runs it: per kind of job, the jobs done,
//! running and left, the time its jobs took, and an estimate of the time left.
//!
//! Every job writes a start record, `OUT/cache/jobs/ID.started` (host, process id, start time),
//! before its work and its completion marker (`ID.done`, [`cache`]) after, so a job's time is the
//! marker's modification time less its start. A job is running while it has a start record and
//! no marker, and its process is alive: checked on this host, taken on trust on another one.
//! After a submission to Slurm, squeue says instead which jobs run. A killed job leaves its
//! record with a dead process; the next attempt writes a new one.
//!
//! The time left is each kind's jobs left at the mean time of that kind's jobs done (a running
//! job less the time it has run), over the number of jobs running at once; kinds with no job
//! done yet are named as not timed.

use std::collections::HashSet;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::time::{Duration, SystemTime};

use serde::{Deserialize, Serialize};

use crate::cache;
use crate::plan::{Kind, PlanFile};
use crate::slurm::{self, Submitted};
use crate::ReproduceError;

/// `OUT/cache/jobs/ID.started`: who started a job and when.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Started {
    pub host: String,
    pub pid: u32,
    /// Seconds since the Unix epoch.
    pub at: f64,
}

impl Started {
    fn path(out: &Path, id: &str) -> PathBuf {
        cache::marker_path(out, id).with_extension("started")
    }

    /// Records that this process starts job `id` now.
    pub fn write(out: &Path, id: &str) -> Result<(), ReproduceError> {
        let started = Started {
            host: this_host(),
            pid: std::process::id(),
            at: unix_seconds(SystemTime::now()),
        };
        let text = serde_json::to_string(&started).expect("a start record always serialises");
        cache::write(&Self::path(out, id), &text)
    }

    fn read(out: &Path, id: &str) -> Option<Self> {
        let text = std::fs::read_to_string(Self::path(out, id)).ok()?;
        serde_json::from_str(&text).ok()
    }

    /// Whether its process still runs: on `host` (this one) its pid is alive; elsewhere it
    /// cannot be told.
    fn alive(&self, host: &str) -> bool {
        if self.host != host {
            return true;
        }
        let Ok(pid) = i32::try_from(self.pid) else {
            return false;
        };
        let pid = nix::unistd::Pid::from_raw(pid);
        // Signal 0 checks that the process exists; EPERM means it does, under another user.
        !matches!(
            nix::sys::signal::kill(pid, None),
            Err(nix::errno::Errno::ESRCH)
        )
    }
}

fn this_host() -> String {
    nix::unistd::gethostname().map_or_else(
        |_| "unknown".into(),
        |name| name.to_string_lossy().into_owned(),
    )
}

fn unix_seconds(t: SystemTime) -> f64 {
    t.duration_since(SystemTime::UNIX_EPOCH)
        .map_or(0.0, |d| d.as_secs_f64())
}

/// One kind's jobs.
#[derive(Debug, Clone)]
pub struct KindStatus {
    pub kind: Kind,
    pub total: usize,
    pub done: usize,
    pub running: usize,
    /// The jobs done with a start record, and their time together.
    pub timed: usize,
    pub busy: Duration,
    /// The work left: the jobs not started at the mean time, the running ones less the time they
    /// have run; `None` while jobs are left and none is timed.
    pub work_left: Option<Duration>,
}

impl KindStatus {
    fn mean(&self) -> Option<Duration> {
        (self.timed > 0).then(|| self.busy / self.timed as u32)
    }
}

/// Where a plan stands.
#[derive(Debug, Clone)]
pub struct Status {
    pub kinds: Vec<KindStatus>,
    pub done: usize,
    pub total: usize,
    /// The running jobs' ids; `None` when the plan was submitted and squeue did not answer.
    pub running: Option<Vec<String>>,
    /// How many jobs of the latest submission are queued or running, if squeue answered.
    pub queued: Option<usize>,
}

/// What the cache says of one job: whether it is done, its start record and its marker's time.
struct JobRecord<'p> {
    id: &'p str,
    kind: Kind,
    done: bool,
    started: Option<Started>,
    ended: Option<SystemTime>,
}

/// The status of the plan in `out`, from its markers and start records and, when it was
/// submitted, squeue.
pub fn status(out: &Path) -> Result<Status, ReproduceError> {
    let plan = PlanFile::read(out)?;
    let submitted = Submitted::read(out);
    let queue = submitted.as_ref().and_then(|s| slurm::squeue(s, &plan));
    let records: Vec<JobRecord> = (plan.jobs.iter())
        .map(|job| {
            let done = PlanFile::done(out, job);
            let marker = cache::marker_path(out, &job.id);
            JobRecord {
                id: &job.id,
                kind: job.kind,
                done,
                started: Started::read(out, &job.id),
                ended: (done.then(|| std::fs::metadata(marker).and_then(|m| m.modified()).ok()))
                    .flatten(),
            }
        })
        .collect();
    let running: Option<Vec<String>> = match (&submitted, &queue) {
        (Some(_), Some((_, running))) => Some(running.clone()),
        (Some(_), None) => None,
        (None, _) => {
            let host = this_host();
            let alive =
                |r: &&JobRecord| !r.done && r.started.as_ref().is_some_and(|s| s.alive(&host));
            Some(
                records
                    .iter()
                    .filter(alive)
                    .map(|r| r.id.to_string())
                    .collect(),
            )
        }
    };
    let ids = running
        .iter()
        .flatten()
        .map(String::as_str)
        .collect::<HashSet<_>>();
    let now = unix_seconds(SystemTime::now());
    let kinds: Vec<KindStatus> = (Kind::ALL.into_iter())
        .map(|kind| kind_status(kind, records.iter().filter(|r| r.kind == kind), &ids, now))
        .collect();
    Ok(Status {
        done: kinds.iter().map(|k| k.done).sum(),
        total: plan.jobs.len(),
        kinds,
        running,
        queued: queue.map(|q| q.0),
    })
}

/// One kind's counts, times and work left from its jobs' records; `running` holds the ids of the
/// jobs running, `now` is in Unix seconds.
fn kind_status<'r, 'p: 'r>(
    kind: Kind,
    records: impl Iterator<Item = &'r JobRecord<'p>>,
    running: &HashSet<&str>,
    now: f64,
) -> KindStatus {
    let seconds = |s: f64| Duration::from_secs_f64(s.max(0.0));
    let mut k = KindStatus {
        kind,
        total: 0,
        done: 0,
        running: 0,
        timed: 0,
        busy: Duration::ZERO,
        work_left: None,
    };
    let mut elapsed = Vec::new();
    for r in records {
        k.total += 1;
        if r.done {
            k.done += 1;
            if let (Some(s), Some(end)) = (&r.started, r.ended) {
                k.timed += 1;
                k.busy += seconds(unix_seconds(end) - s.at);
            }
        } else if running.contains(r.id) {
            k.running += 1;
            elapsed.push(seconds(r.started.as_ref().map_or(0.0, |s| now - s.at)));
        }
    }
    let waiting = (k.total - k.done - k.running) as u32;
    k.work_left = match (k.mean(), k.done == k.total) {
        (_, true) => Some(Duration::ZERO),
        (None, false) => None,
        (Some(mean), false) => {
            let running_left = elapsed.iter().map(|&e| mean.saturating_sub(e));
            Some(mean * waiting + running_left.sum::<Duration>())
        }
    };
    k
}

impl Status {
    pub fn finished(&self) -> bool {
        self.done == self.total
    }

    /// The status in lines: a table of kinds, then the whole, the estimate and the running jobs.
    pub fn describe(&self) -> String {
        let mut s = String::new();
        let _ = writeln!(
            s,
            "{:>13} {:>5} {:>7} {:>5} {:>11} {:>10}",
            "kind", "done", "running", "left", "mean_s", "busy_min"
        );
        for k in &self.kinds {
            let mean = k
                .mean()
                .map_or("-".into(), |m| format!("{:.1}", m.as_secs_f64()));
            let _ = writeln!(
                s,
                "{:>13} {:>5} {:>7} {:>5} {mean:>11} {:>10.1}",
                k.kind.name(),
                k.done,
                k.running,
                k.total - k.done - k.running,
                k.busy.as_secs_f64() / 60.0
            );
        }
        let running = match &self.running {
            Some(ids) => ids.len().to_string(),
            None => "unknown (squeue did not answer)".into(),
        };
        let _ = writeln!(
            s,
            "done {} of {} jobs, running {running}, left {}; {}",
            self.done,
            self.total,
            self.total - self.done,
            self.eta_text()
        );
        for id in self.running.iter().flatten() {
            let _ = writeln!(s, "  running: {id}");
        }
        s
    }

    /// The time left: the work left over the jobs running at once.
    pub fn eta_text(&self) -> String {
        if self.finished() {
            return "finished".into();
        }
        let parallel = self.running.as_ref().map_or(0, Vec::len);
        if parallel == 0 {
            return "nothing running".into();
        }
        let work: Duration = self.kinds.iter().filter_map(|k| k.work_left).sum();
        let untimed: Vec<&str> = (self.kinds.iter())
            .filter(|k| k.work_left.is_none())
            .map(|k| k.kind.name())
            .collect();
        let minutes = work.as_secs_f64() / 60.0 / parallel as f64;
        match untimed.is_empty() {
            true => format!("about {minutes:.1} min left"),
            false => format!(
                "about {minutes:.1} min left, and {} not timed yet",
                untimed.join(", ")
            ),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_start_record_of_a_live_process_is_alive_and_of_a_dead_one_is_not() {
        let mine = Started {
            host: this_host(),
            pid: std::process::id(),
            at: 0.0,
        };
        let host = this_host();
        assert!(mine.alive(&host));
        let mut child = std::process::Command::new("true").spawn().unwrap();
        let pid = child.id();
        child.wait().unwrap();
        let dead = Started {
            pid,
            ..mine.clone()
        };
        assert!(!dead.alive(&host));
        let elsewhere = Started {
            host: format!("{}-elsewhere", this_host()),
            ..dead
        };
        assert!(elsewhere.alive(&host));
    }
}
