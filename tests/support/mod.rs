//! What the end-to-end tests share: the small run config, deadlines, and processes that are
//! killed when a test ends, passed or failed.

// Each test file compiles this module on its own and uses a part of it.
#![allow(dead_code)]

use std::collections::BTreeMap;
use std::path::Path;
use std::process::{Child, Command};
use std::time::{Duration, Instant};

use uavmeta_proto::dataset::DatasetReader;

pub const BIN: &str = env!("CARGO_BIN_EXE_uavmeta");

/// A small, quick run: two meta-train tasks and the unseen one, heuristic actors, a tiny network.
pub const SMALL: &str = r#"
[world]
layout_seed = 7

[[tasks]]
name = "lambda-0"
lambda = 0.0
role = "meta-train"

[[tasks]]
name = "lambda-100"
lambda = 100.0
role = "meta-train"

[[tasks]]
name = "lambda-300"
lambda = 300.0
role = "meta-test"

[collect]
policy = "random"
transitions = 300

[learner]
hidden = [16, 16]
epochs = 2
eval_episodes = 2

[meta]
meta_epochs = 4
checkpoint_every = 2
support_batch_size = 16
query_batch_size = 16
eval_every = 0

[run]
transitions_per_message = 16

# The planner's reference row only has to exist in these runs: one narrow search instead of the
# default's four of width 256 (about half a minute per launch on the default world).
[planner]
beam_width = 16
h_power_weights = [0.25]
"#;

/// `--set`s turning the small run into one like the paper's: each actor first trains an online
/// DQN agent (a small one, for a few thousand steps), then sends a sample of its replay buffer.
pub const DQN_RUN: &[&str] = &[
    "collect.policy=dqn-online",
    "collect.dqn.steps=6000",
    "collect.dqn.hidden=[64, 64]",
    "collect.dqn.learning_starts=500",
    "collect.dqn.eps_decay_steps=3000",
];

/// The one place deadlines come from: `seconds` is what a step takes on a quiet machine, with a
/// margin; the deadline is that times `UAVMETA_TEST_PATIENCE` (default 3), so a loaded machine
/// (`make test` beside a build and two busy loops: docs/TESTING.md) is slow, never failed. Every
/// wait polls its condition and returns as soon as it holds, so patience costs nothing when the
/// machine is fast.
pub fn within(seconds: u64) -> Duration {
    let patience = std::env::var("UAVMETA_TEST_PATIENCE")
        .ok()
        .map(|p| {
            p.parse::<u64>().unwrap_or_else(|_| {
                panic!("UAVMETA_TEST_PATIENCE=`{p}`: expected a whole factor such as 3")
            })
        })
        .unwrap_or(3);
    Duration::from_secs(seconds * patience)
}

/// `--config` (the small config, written into `dir`), `--set run.dir=<run>` and `overrides`.
pub fn config_args(dir: &Path, run: &Path, overrides: &[&str]) -> Vec<String> {
    let config = dir.join("small.toml");
    std::fs::write(&config, SMALL).expect("write the test config");
    let mut args = vec![
        "--config".to_string(),
        config.display().to_string(),
        "--set".into(),
        format!("run.dir={}", run.display()),
    ];
    for o in overrides {
        args.push("--set".into());
        args.push(o.to_string());
    }
    args
}

/// A process the test started; killed (with its process group) when dropped. Its output goes to
/// files, so a chatty process never blocks on a full pipe.
pub struct Proc {
    child: Child,
    pub name: String,
    out: tempfile::NamedTempFile,
    err: tempfile::NamedTempFile,
}

/// What a finished process printed.
pub struct Finished {
    pub status: std::process::ExitStatus,
    pub stdout: String,
    pub stderr: String,
}

impl Proc {
    /// `uavmeta` with `args`.
    pub fn spawn(name: &str, args: &[String]) -> Proc {
        Proc::spawn_program(BIN, name, args)
    }

    /// `program` with `args`, in a process group of its own.
    pub fn spawn_program(program: &str, name: &str, args: &[String]) -> Proc {
        use std::os::unix::process::CommandExt;
        let keep = std::env::var_os("UAVMETA_TEST_KEEP").is_some();
        let file = |suffix: &str| {
            tempfile::Builder::new()
                .prefix(&format!("uavmeta-{name}-"))
                .suffix(suffix)
                .disable_cleanup(keep)
                .tempfile()
        };
        let out = file(".out").expect("stdout file");
        let err = file(".err").expect("stderr file");
        let child = Command::new(program)
            .args(args)
            .stdout(out.reopen().expect("stdout"))
            .stderr(err.reopen().expect("stderr"))
            .process_group(0)
            .spawn()
            .unwrap_or_else(|e| panic!("cannot start {name}: {e}"));
        Proc {
            child,
            name: name.to_string(),
            out,
            err,
        }
    }

    pub fn pid(&self) -> i32 {
        self.child.id() as i32
    }

    /// Waits for the process to exit, at most `timeout`.
    pub fn wait(mut self, timeout: Duration) -> Finished {
        let start = Instant::now();
        let status = loop {
            if let Some(status) = self.child.try_wait().expect("try_wait") {
                break status;
            }
            assert!(
                start.elapsed() < timeout,
                "{} still running after {timeout:?}; its stderr:\n{}",
                self.name,
                self.stderr()
            );
            std::thread::sleep(Duration::from_millis(50));
        };
        Finished {
            status,
            stdout: std::fs::read_to_string(self.out.path()).expect("stdout"),
            stderr: std::fs::read_to_string(self.err.path()).expect("stderr"),
        }
    }

    /// Waits for the process to exit, at most `timeout`, and requires success.
    pub fn succeeds(self, timeout: Duration) -> Finished {
        let name = self.name.clone();
        let finished = self.wait(timeout);
        assert!(
            finished.status.success(),
            "{name} failed ({}); its stderr:\n{}",
            finished.status,
            finished.stderr
        );
        finished
    }

    /// Waits until the process has logged `needle`, at most `timeout`; fails at once if the
    /// process exits first. Either failure shows what it logged.
    pub fn logs(&mut self, needle: &str, timeout: Duration) {
        let start = Instant::now();
        while !self.stderr().contains(needle) {
            if let Some(status) = self.child.try_wait().expect("try_wait") {
                panic!(
                    "{} exited ({status}) before logging `{needle}`; its stderr:\n{}",
                    self.name,
                    self.stderr()
                );
            }
            assert!(
                start.elapsed() < timeout,
                "{} did not log `{needle}` within {timeout:?}; its stderr:\n{}",
                self.name,
                self.stderr()
            );
            std::thread::sleep(Duration::from_millis(100));
        }
    }

    pub fn running(&mut self) -> bool {
        matches!(self.child.try_wait(), Ok(None))
    }

    /// What the process has written to stderr (its log lines) so far.
    pub fn stderr(&self) -> String {
        std::fs::read_to_string(self.err.path()).unwrap_or_default()
    }

    pub fn signal(&self, signal: i32) {
        // SAFETY: a signal to the process group this test created.
        unsafe { libc::killpg(self.pid(), signal) };
    }
}

impl Drop for Proc {
    fn drop(&mut self) {
        if self.running() {
            self.signal(libc::SIGKILL);
            let _ = self.child.wait();
        }
    }
}

pub fn run_dir(prefix: &str) -> tempfile::TempDir {
    tempfile::Builder::new()
        .prefix(prefix)
        .disable_cleanup(std::env::var_os("UAVMETA_TEST_KEEP").is_some())
        .tempdir()
        .expect("temp dir")
}

pub fn wait_until(what: &str, timeout: Duration, mut done: impl FnMut() -> bool) {
    let start = Instant::now();
    while !done() {
        assert!(
            start.elapsed() < timeout,
            "timed out after {timeout:?} waiting for {what}"
        );
        std::thread::sleep(Duration::from_millis(100));
    }
}

pub fn launch(dir: &Path, run: &Path, overrides: &[&str]) -> Proc {
    let mut args = vec!["launch".to_string()];
    args.extend(config_args(dir, run, overrides));
    Proc::spawn("launch", &args)
}

/// The pid of the launched child whose command line contains all of `needles`.
pub fn child_pid(needles: &[&str]) -> Option<i32> {
    child_pids(needles).into_iter().next()
}

/// The pids of the processes whose command line contains all of `needles`.
pub fn child_pids(needles: &[&str]) -> Vec<i32> {
    let Ok(entries) = std::fs::read_dir("/proc") else {
        return Vec::new();
    };
    entries
        .filter_map(|entry| {
            let entry = entry.ok()?;
            let pid = entry.file_name().to_string_lossy().parse::<i32>().ok()?;
            let cmdline = std::fs::read(entry.path().join("cmdline")).ok()?;
            let cmdline = String::from_utf8_lossy(&cmdline).replace('\0', " ");
            needles.iter().all(|n| cmdline.contains(n)).then_some(pid)
        })
        .collect()
}

/// A tool a test needs (promtool, prometheus, tmux) is missing: under `CI=true` that fails the
/// test (`make test` installs them); elsewhere the test skips what needs it, saying so.
pub fn missing_tool(tool: &str, error: &std::io::Error) {
    let ci = std::env::var("CI").is_ok_and(|ci| ci == "true");
    assert!(!ci, "{tool}, required under CI=true: {error}");
    eprintln!("skipped: {tool} is not installed ({error}); `make test` installs it");
}

/// Every dataset file of a run: per task, per actor, the sorted sequence numbers.
pub fn dataset_seqs(run: &Path) -> BTreeMap<String, BTreeMap<u32, Vec<u64>>> {
    let mut out = BTreeMap::new();
    for entry in std::fs::read_dir(run.join("datasets")).expect("datasets dir") {
        let path = entry.expect("entry").path();
        let reader = DatasetReader::open(&path).unwrap_or_else(|e| panic!("{e}"));
        let mut per_actor: BTreeMap<u32, Vec<u64>> = BTreeMap::new();
        for t in reader.transitions() {
            per_actor.entry(t.actor).or_default().push(t.seq);
        }
        for seqs in per_actor.values_mut() {
            let n = seqs.len();
            seqs.sort_unstable();
            seqs.dedup();
            assert_eq!(
                seqs.len(),
                n,
                "{}: a transition is stored twice",
                path.display()
            );
        }
        out.insert(reader.header().task_name.clone(), per_actor);
    }
    out
}

/// The Python the consumer tests run: the active virtualenv's, else the libtorch virtualenv's
/// (`VENV/lib/pythonX.Y/site-packages/torch`, which `.libtorch` points into, made by `make`), else
/// the one on PATH.
pub fn venv_python() -> std::path::PathBuf {
    if let Some(venv) = std::env::var_os("VIRTUAL_ENV") {
        return std::path::PathBuf::from(venv).join("bin/python");
    }
    let libtorch = Path::new(env!("CARGO_MANIFEST_DIR")).join(".libtorch");
    match std::fs::canonicalize(libtorch)
        .ok()
        .and_then(|torch| torch.ancestors().nth(4).map(Path::to_path_buf))
    {
        Some(venv) if venv.join("bin/python").exists() => venv.join("bin/python"),
        _ => std::path::PathBuf::from("python3"),
    }
}

/// Whether `python` imports `modules` (comma-separated, as in an import statement). Without them
/// the caller skips, saying why and that `installer` installs them; under `CI=true` it fails.
pub fn python_imports(python: &Path, modules: &str, installer: &str) -> bool {
    let imported = Command::new(python)
        .args(["-c", &format!("import {modules}")])
        .output();
    let why = match imported {
        Ok(out) if out.status.success() => return true,
        Ok(out) => String::from_utf8_lossy(&out.stderr).into_owned(),
        Err(e) => e.to_string(),
    };
    let why = format!(
        "{} cannot import {modules} (`{installer}` installs them): {why}",
        python.display()
    );
    assert!(
        std::env::var("CI").map_or(true, |ci| ci != "true"),
        "required under CI=true: {why}"
    );
    eprintln!("skipped: {why}");
    false
}

/// The fields of `method`'s row on lambda-300 in the table of `text` that follows the line
/// starting with `after` (the first table when `after` is empty): task, method, epoch, return,
/// `±`, its interval, vs planner, ...
pub fn table_row<'a>(text: &'a str, after: &str, method: &str) -> Vec<&'a str> {
    let rest = &text[text
        .find(after)
        .unwrap_or_else(|| panic!("no `{after}` in:\n{text}"))..];
    rest.lines()
        .find(|l| l.starts_with("lambda-300") && l.split_whitespace().nth(1) == Some(method))
        .unwrap_or_else(|| panic!("no {method} row after `{after}` in:\n{text}"))
        .split_whitespace()
        .collect()
}

/// The return of `method` on lambda-300 in the table of `text` that follows the line starting
/// with `after` (the first table when `after` is empty).
pub fn table_return(text: &str, after: &str, method: &str) -> f64 {
    table_row(text, after, method)[3].parse().unwrap()
}
