//! `uavmeta launch` as a person watching it sees it: in a 160x40 terminal (tmux), its display
//! must move from the start (the actors' online DQN agents training), draw each task's row once,
//! and leave only the results table when the run ends.
//!
//! tmux comes from Debian's `tmux` package (`make test` installs it); under `CI=true` it must be
//! installed, elsewhere the test skips, saying so.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};
use std::time::{Duration, Instant};

mod support;
use support::{config_args, missing_tool, run_dir, within, BIN, DQN_RUN};

const TASKS: [&str; 3] = ["lambda-0", "lambda-100", "lambda-300"];

/// A tmux server of its own (its socket in the test's directory) running one command in a
/// 160x40 window; the command is stopped and the server ended when dropped.
struct Tmux {
    socket: PathBuf,
}

impl Tmux {
    /// Starts `command` in a new 160x40 session; `None` (after saying why) without tmux.
    fn start(dir: &Path, command: &[String]) -> Option<Tmux> {
        let conf = dir.join("tmux.conf");
        // The pane stays after the command exits, so its last screen can be read.
        std::fs::write(
            &conf,
            "set -g remain-on-exit on\nset -g history-limit 10000\n",
        )
        .expect("write the tmux config");
        let tmux = Tmux {
            socket: dir.join("tmux.socket"),
        };
        let mut args = vec!["-f".to_string(), conf.display().to_string()];
        args.extend(["new-session", "-d", "-x", "160", "-y", "40", "--"].map(String::from));
        args.extend_from_slice(command);
        match tmux.run(&args) {
            Ok(out) => assert!(out.status.success(), "tmux new-session: {out:?}"),
            Err(error) => {
                missing_tool("tmux", &error);
                return None;
            }
        }
        Some(tmux)
    }

    fn run(&self, args: &[String]) -> std::io::Result<Output> {
        Command::new("tmux")
            .arg("-S")
            .arg(&self.socket)
            .args(args)
            .output()
    }

    /// A format of the pane, such as `#{pane_dead}`.
    fn pane(&self, format: &str) -> String {
        let out = self.run(&["display-message".into(), "-p".into(), format.into()]);
        let out = out.expect("tmux display-message");
        String::from_utf8_lossy(&out.stdout).trim().to_string()
    }

    /// Everything the pane shows and has scrolled off, line by line of the terminal (not joined:
    /// the rows fill the width, which tmux would take for wrapped lines).
    fn screen(&self) -> String {
        let args = ["capture-pane", "-p", "-S", "-"].map(String::from);
        let out = self.run(&args).expect("tmux capture-pane");
        assert!(out.status.success(), "tmux capture-pane: {out:?}");
        String::from_utf8_lossy(&out.stdout).into_owned()
    }

    fn exited(&self) -> bool {
        self.pane("#{pane_dead}") == "1"
    }
}

impl Drop for Tmux {
    fn drop(&mut self) {
        // A launch still running is stopped as Ctrl-C would, so that it stops its children in
        // order, before the server goes.
        if !self.exited() {
            if let Ok(pid) = self.pane("#{pane_pid}").parse::<i32>() {
                // SAFETY: a signal to the launch this test started.
                unsafe { libc::kill(pid, libc::SIGTERM) };
                let start = Instant::now();
                while !self.exited() && start.elapsed() < within(60) {
                    std::thread::sleep(Duration::from_millis(100));
                }
            }
        }
        let _ = self.run(&["kill-server".into()]);
    }
}

/// The display's row of each task on `screen`, in order: lines that start with the task's name
/// and draw a bar (the results table's lines start with it too, but draw none).
fn task_rows(screen: &str) -> Vec<Vec<&str>> {
    let rows = |task: &str| {
        screen
            .lines()
            .filter(|l| l.split_whitespace().next() == Some(task) && l.contains(" ["))
            .collect()
    };
    TASKS.iter().map(|task| rows(task)).collect()
}

/// No task's row is drawn twice, anywhere on `screen` or above it.
fn assert_each_row_once(screen: &str) {
    for (task, rows) in TASKS.iter().zip(task_rows(screen)) {
        assert!(
            rows.len() <= 1,
            "{task}'s row drawn {} times:\n{screen}",
            rows.len()
        );
    }
}

/// Captures the screen until `done` holds for it, checking every capture for rows drawn twice;
/// returns the screen `done` held for, and fails with the last one at the deadline.
fn watch(tmux: &Tmux, what: &str, timeout: Duration, mut done: impl FnMut(&str) -> bool) -> String {
    let start = Instant::now();
    loop {
        let screen = tmux.screen();
        assert_each_row_once(&screen);
        if done(&screen) {
            return screen;
        }
        assert!(
            start.elapsed() < timeout,
            "timed out after {timeout:?} waiting for {what}; the screen:\n{screen}"
        );
        std::thread::sleep(Duration::from_millis(100));
    }
}

#[test]
fn the_launch_display_moves_from_the_start_and_leaves_only_the_results_table() {
    let dir = run_dir("e2e-terminal-");
    let run = dir.path().join("run");
    let mut command = vec![BIN.to_string(), "launch".into()];
    command.extend(config_args(dir.path(), &run, DQN_RUN));
    let Some(tmux) = Tmux::start(dir.path(), &command) else {
        return;
    };

    let first = watch(&tmux, "every task's row", within(60), |screen| {
        task_rows(screen).iter().all(|rows| rows.len() == 1)
    });
    // The agents' training shows (step, epsilon, return) as soon as it moves.
    let training = |screen: &str| screen.contains("training online DQN: step ");
    let mut trained = training(&first);
    watch(&tmux, "the task rows to change", within(10), |screen| {
        trained |= training(screen);
        task_rows(screen) != task_rows(&first)
    });
    watch(
        &tmux,
        "the online DQN agents' progress",
        within(60),
        |screen| {
            trained |= training(screen);
            trained
        },
    );

    let last = watch(&tmux, "the launch to end", within(240), |_| tmux.exited());
    // A launch that ends well prints its results table; tmux 3.3a does not always fill in
    // `pane_dead_status` for a pane that has died, so the table is what tells.
    assert!(
        last.contains("(0 restarts)") && last.contains("cql-maml"),
        "the launch failed:\n{last}"
    );
    assert!(
        task_rows(&last).iter().all(Vec::is_empty),
        "display rows left behind:\n{last}"
    );
    for gone in ["meta-learner [", "evaluator waiting", " returns: "] {
        assert!(!last.contains(gone), "`{gone}` left behind:\n{last}");
    }
    assert!(
        last.lines()
            .any(|l| l.starts_with("lambda-300") && l.contains("maml-init")),
        "no results table:\n{last}"
    );
}
