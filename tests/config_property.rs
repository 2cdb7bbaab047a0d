//! No value of any config key aborts the binary (issue #85): for every numeric or list key of the
//! saved default config, values drawn from its whole type (0, 1, negative, huge, NaN and the
//! infinities where a float) go through `--set` to the subcommands that read the key's section.
//! Each case ends one of three ways, or the test fails naming it: the binary exits 0; it exits
//! with a one-line error naming the key; or it is still making progress (its CPU time or its
//! output grows) after [`CUTOFF`], when it passes and is stopped. Never a signal, a panic or a
//! hang.
//!
//! The memory the processes may use is fixed by `UAVMETA_MEMORY_BYTES` (and the disk by
//! `UAVMETA_DISK_BYTES`), so every machine gives the same answers; each process's address
//! space is also capped, so that an allocation the estimate misses fails (and the case with it)
//! rather than taking the memory of whatever else runs here.

mod support;

use std::os::unix::process::CommandExt;
use std::path::{Path, PathBuf};
use std::process::{Command, ExitStatus, Stdio};
use std::time::{Duration, Instant};

use rand::seq::IndexedRandom;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use support::{run_dir, within, BIN};

/// How long a case runs before "still making progress" is enough.
const CUTOFF: Duration = Duration::from_secs(3);
/// The memory every case's process may use, by `UAVMETA_MEMORY_BYTES`: the default config's
/// jobs need a few hundred MB.
const MEMORY_BYTES: u64 = 2_000_000_000;
/// The free disk every case sees, by `UAVMETA_DISK_BYTES`.
const DISK_BYTES: u64 = 20_000_000_000;
/// Each process's address space: libtorch maps about 1.5 GB of it at start.
const ADDRESS_SPACE_BYTES: u64 = 8 << 30;

/// Values drawn per key beside the huge one every key gets.
const DRAWN: usize = 1;

const INTEGERS: &[&str] = &["0", "1", "-1", "1000000000000", "9223372036854775807"];
const HUGE_INTEGER: &str = "1000000000";
const FLOATS: &[&str] = &["0.0", "1.0", "-1.0", "nan", "inf", "-inf", "1e-300"];
const HUGE_FLOAT: &str = "1e300";
const INTEGER_LISTS: &[&str] = &["[]", "[0]", "[1]", "[-1]", "[1000000000]"];
const HUGE_INTEGER_LIST: &str = "[200000, 200000]";
const FLOAT_LISTS: &[&str] = &["[]", "[0.0]", "[-1.0]", "[nan]", "[inf]"];
const HUGE_FLOAT_LIST: &str = "[1e300]";
const STRING_LISTS: &[&str] = &[
    "[]",
    "[\"\"]",
    "[\"x\"]",
    "[\"lambda-300\", \"lambda-300\"]",
];

/// A key of the saved default config and the values its cases set.
struct Key {
    name: String,
    values: Vec<String>,
}

/// The subcommands a test runs, each small enough to finish in seconds at the defaults.
#[derive(Clone, Copy, Debug)]
enum Sub {
    Rollout,
    Plan,
    Collect,
    CollectDqn,
    Train,
    MetaTrain,
    Context,
}

/// Which subcommands read a key: those of its section.
fn readers(key: &str) -> &'static [Sub] {
    let section = key.split('.').next().unwrap_or_default();
    match section {
        "world" | "tasks" => &[Sub::Rollout],
        "collect" if key.starts_with("collect.dqn.") => &[Sub::CollectDqn],
        "collect" => &[Sub::Collect],
        "learner" => &[Sub::Train],
        "meta" => &[Sub::MetaTrain],
        "context" => &[Sub::Context],
        "planner" => &[Sub::Plan],
        "run" => &[Sub::Collect, Sub::Train],
        // The tunnel's keys are used by a launch and the tunnel alone, which no case starts
        // (tests/remote.rs and tests/hostile.rs run them); every subcommand checks their rules
        // when it loads the config, and `collect` is the cheapest to load it.
        "tunnel" => &[Sub::Collect],
        _ => &[],
    }
}

/// What every case shares: a directory, the default config's shots and datasets.
struct Fixture {
    dir: PathBuf,
    shots: PathBuf,
    datasets: PathBuf,
}

impl Fixture {
    /// Collects one small random dataset per task of the default config; the first one's saved
    /// config is the config whose keys the test enumerates.
    fn new(dir: &Path) -> (Self, toml::Table) {
        let datasets = dir.join("datasets");
        let tasks = default_config_tasks();
        for task in &tasks {
            let out = datasets.join(format!("{task}.uavds"));
            let status = command(&[
                "collect",
                "--task",
                task,
                "--policy",
                "random",
                "--transitions",
                "300",
                "--out",
                out.to_str().expect("utf-8 path"),
            ])
            .stdout(Stdio::null())
            .status()
            .expect("collect runs");
            assert!(status.success(), "collecting {task}'s dataset: {status}");
        }
        let shots = datasets.join("lambda-300.uavds");
        let saved = datasets.join("lambda-300.uavds.config.toml");
        let text = std::fs::read_to_string(&saved).expect("collect saves its config");
        let config = text
            .parse::<toml::Table>()
            .expect("the saved config is TOML");
        let fixture = Self {
            dir: dir.to_path_buf(),
            shots,
            datasets,
        };
        (fixture, config)
    }

    /// The arguments of `sub` for case `case`, before the case's `--set`.
    fn args(&self, sub: Sub, case: usize) -> Vec<String> {
        let out = self.dir.join(format!("case-{case}"));
        let out = out.to_str().expect("utf-8 path").to_string();
        let shots = self.shots.to_str().expect("utf-8 path").to_string();
        let datasets = self.datasets.to_str().expect("utf-8 path").to_string();
        let task = ["--task", "lambda-300"];
        let args: Vec<&str> = match sub {
            Sub::Rollout => [&["env", "rollout"][..], &task, &["--episodes", "1"]].concat(),
            Sub::Plan => [
                &["env", "rollout"][..],
                &task,
                &["--episodes", "1", "--policy", "planner"],
            ]
            .concat(),
            Sub::Collect => [
                &["collect"][..],
                &task,
                &["--policy", "random", "--transitions", "10", "--out", &out],
            ]
            .concat(),
            Sub::CollectDqn => [
                &["collect"][..],
                &task,
                &[
                    "--policy",
                    "dqn-online",
                    "--transitions",
                    "10",
                    "--out",
                    &out,
                ],
                &["--set", "collect.dqn.steps=1100"],
            ]
            .concat(),
            Sub::Train => [
                &["train", "--algo", "dyna-cql"][..],
                &task,
                &["--dataset", &shots, "--shots", "100", "--out", &out],
                &[
                    "--set",
                    "learner.epochs=1",
                    "--set",
                    "learner.model_rows=100",
                ],
            ]
            .concat(),
            Sub::MetaTrain | Sub::Context => {
                let learner = match sub {
                    Sub::Context => "context",
                    _ => "maml",
                };
                [
                    &["meta-train", "--learner", learner][..],
                    &["--datasets", &datasets, "--out", &out],
                    &[
                        "--set",
                        "meta.meta_epochs=1",
                        "--set",
                        "context.encoder_steps=10",
                    ],
                    &["--set", "learner.epochs=1"],
                ]
                .concat()
            }
        };
        args.into_iter().map(String::from).collect()
    }
}

/// The names of the default config's tasks, from `configs/default.toml`.
fn default_config_tasks() -> Vec<String> {
    let text = std::fs::read_to_string("configs/default.toml").expect("configs/default.toml");
    let table = text
        .parse::<toml::Table>()
        .expect("the default config is TOML");
    let tasks = table["tasks"].as_array().expect("[[tasks]]");
    let names = tasks
        .iter()
        .map(|t| t["name"].as_str().expect("a task name"));
    names.map(String::from).collect()
}

/// Every numeric or list key of `table`, dotted, with the values its cases set: the huge value
/// of its type and [`DRAWN`] more drawn from the rest. Of the tasks, the first stands for all.
fn keys(table: &toml::Table, prefix: &str, rng: &mut ChaCha8Rng, out: &mut Vec<Key>) {
    for (name, value) in table {
        let name = format!("{prefix}{name}");
        let (huge, pool) = match value {
            toml::Value::Table(inner) => {
                keys(inner, &format!("{name}."), rng, out);
                continue;
            }
            toml::Value::Array(items) if items.iter().all(toml::Value::is_table) => {
                if let Some(toml::Value::Table(first)) = items.first() {
                    keys(first, &format!("{name}.0."), rng, out);
                }
                continue;
            }
            toml::Value::Integer(_) => (Some(HUGE_INTEGER), INTEGERS),
            toml::Value::Float(_) => (Some(HUGE_FLOAT), FLOATS),
            toml::Value::Array(items) => match items.first() {
                Some(toml::Value::Float(_)) => (Some(HUGE_FLOAT_LIST), FLOAT_LISTS),
                Some(toml::Value::String(_)) => (None, STRING_LISTS),
                // An empty list of the default (`tunnel.wait_for_hosts`) holds names.
                None => (None, STRING_LISTS),
                _ => (Some(HUGE_INTEGER_LIST), INTEGER_LISTS),
            },
            _ => continue,
        };
        let drawn = pool.choose_multiple(rng, DRAWN);
        let values = huge.into_iter().chain(drawn.copied());
        out.push(Key {
            name,
            values: values.map(String::from).collect(),
        });
    }
}

/// `uavmeta` with `args`, the fixed memory and disk, and the capped address space.
fn command(args: &[&str]) -> Command {
    let mut command = Command::new(BIN);
    command
        .args(args)
        .env("UAVMETA_MEMORY_BYTES", MEMORY_BYTES.to_string())
        .env("UAVMETA_DISK_BYTES", DISK_BYTES.to_string())
        .env("RUST_LOG", "warn")
        .process_group(0);
    // SAFETY: setrlimit is async-signal-safe; it only lowers this child's own limit.
    unsafe {
        command.pre_exec(|| {
            let limit = libc::rlimit {
                rlim_cur: ADDRESS_SPACE_BYTES,
                rlim_max: ADDRESS_SPACE_BYTES,
            };
            libc::setrlimit(libc::RLIMIT_AS, &limit);
            Ok(())
        });
    }
    command
}

/// How one case ended.
enum Outcome {
    Exited(ExitStatus, String),
    Progressing,
    Hung(String),
}

/// Runs `args` until it exits, or past [`CUTOFF`] while its CPU time or output grows.
fn run_case(args: &[String], dir: &Path, case: usize) -> Outcome {
    let err_path = dir.join(format!("case-{case}.err"));
    let out_path = dir.join(format!("case-{case}.out"));
    let args: Vec<&str> = args.iter().map(String::as_str).collect();
    let mut child = command(&args)
        .stdout(std::fs::File::create(&out_path).expect("stdout file"))
        .stderr(std::fs::File::create(&err_path).expect("stderr file"))
        .spawn()
        .expect("uavmeta starts");
    let pid = child.id() as i32;
    let stderr = || std::fs::read_to_string(&err_path).unwrap_or_default();
    let start = Instant::now();
    let mut seen: Option<(u64, u64)> = None;
    let outcome = loop {
        if let Some(status) = child.try_wait().expect("try_wait") {
            break Outcome::Exited(status, stderr());
        }
        if start.elapsed() >= CUTOFF {
            let now = (cpu_ticks(pid), output_bytes(&[&out_path, &err_path]));
            match seen {
                Some(before) if now.0 > before.0 || now.1 > before.1 => break Outcome::Progressing,
                None => seen = Some(now),
                Some(_) if start.elapsed() > CUTOFF + within(5) => break Outcome::Hung(stderr()),
                Some(_) => {}
            }
        }
        std::thread::sleep(Duration::from_millis(50));
    };
    // SAFETY: a signal to the process group this test created.
    unsafe { libc::killpg(pid, libc::SIGKILL) };
    let _ = child.wait();
    outcome
}

/// User and system CPU time of `pid`, in clock ticks.
fn cpu_ticks(pid: i32) -> u64 {
    let stat = std::fs::read_to_string(format!("/proc/{pid}/stat")).unwrap_or_default();
    let after_name = stat.rsplit_once(')').map_or("", |(_, rest)| rest);
    let fields: Vec<&str> = after_name.split_whitespace().collect();
    // Fields 14 and 15 of stat(5), counted from the state (field 3) here.
    let tick = |i: usize| {
        fields
            .get(i)
            .and_then(|f| f.parse::<u64>().ok())
            .unwrap_or(0)
    };
    tick(11) + tick(12)
}

fn output_bytes(files: &[&Path]) -> u64 {
    let size = |f: &&Path| std::fs::metadata(f).map_or(0, |m| m.len());
    files.iter().map(size).sum()
}

/// Why a case failed, or `None` where it passed.
fn judge(key: &str, outcome: &Outcome) -> Option<String> {
    match outcome {
        Outcome::Progressing => None,
        Outcome::Hung(stderr) => Some(format!("hung, no CPU or output; stderr:\n{stderr}")),
        Outcome::Exited(status, stderr) => {
            if status.success() {
                return None;
            }
            if status.code().is_none() || stderr.contains("panicked") {
                return Some(format!("{status}; stderr:\n{}", tail(stderr)));
            }
            let errors: Vec<&str> = stderr
                .lines()
                .filter(|l| l.starts_with("uavmeta: "))
                .collect();
            let indexed = indexed_form(key);
            match errors[..] {
                [line] if line.contains(key) || line.contains(&indexed) => {
                    let after = stderr.split_once(line).map_or("", |(_, rest)| rest);
                    match after.trim().is_empty() {
                        true => None,
                        false => Some(format!("an error of more than one line:\n{}", tail(stderr))),
                    }
                }
                _ => Some(format!(
                    "{status} without a one-line error naming `{key}`:\n{}",
                    tail(stderr)
                )),
            }
        }
    }
}

/// `tasks.0.lambda` as garde names it, `tasks[0].lambda`.
fn indexed_form(key: &str) -> String {
    let parts: Vec<&str> = key.split('.').collect();
    let mut out = String::new();
    for part in parts {
        match part.parse::<usize>() {
            Ok(i) => out.push_str(&format!("[{i}]")),
            Err(_) if out.is_empty() => out.push_str(part),
            Err(_) => out.push_str(&format!(".{part}")),
        }
    }
    out
}

fn tail(text: &str) -> String {
    let lines: Vec<&str> = text.lines().collect();
    lines[lines.len().saturating_sub(12)..].join("\n")
}

#[test]
fn no_value_of_any_config_key_aborts_the_binary() {
    let dir = run_dir("uavmeta-config-property-");
    let (fixture, config) = Fixture::new(dir.path());
    let mut rng = ChaCha8Rng::seed_from_u64(85);
    let mut all = Vec::new();
    keys(&config, "", &mut rng, &mut all);
    assert!(
        all.iter().any(|k| k.name == "collect.dqn.replay_capacity")
            && all.iter().any(|k| k.name == "learner.hidden"),
        "the saved default config's keys were not found"
    );
    let only = std::env::var("UAVMETA_TEST_KEYS").ok();
    let mut failures = Vec::new();
    let (mut cases, mut refused, mut progressing) = (0, 0, 0);
    let wanted = |k: &&Key| {
        only.as_ref()
            .is_none_or(|o| o.split(',').any(|w| k.name.starts_with(w)))
    };
    for key in all.iter().filter(wanted) {
        for value in &key.values {
            for &sub in readers(&key.name) {
                cases += 1;
                let mut args = fixture.args(sub, cases);
                args.push("--set".into());
                args.push(format!("{}={value}", key.name));
                let outcome = run_case(&args, dir.path(), cases);
                match &outcome {
                    Outcome::Progressing => progressing += 1,
                    Outcome::Exited(status, _) if status.code().is_some_and(|c| c != 0) => {
                        refused += 1
                    }
                    _ => {}
                }
                if let Some(why) = judge(&key.name, &outcome) {
                    let case = format!(
                        "{} = {value} ({sub:?}: uavmeta {})",
                        key.name,
                        args.join(" ")
                    );
                    eprintln!("FAILED {case}: {why}\n");
                    failures.push(case);
                }
                // Each case's outputs go; the directory keeps only the fixture.
                let _ = std::fs::remove_dir_all(dir.path().join(format!("case-{cases}")));
            }
        }
    }
    eprintln!(
        "{cases} cases over {} keys: {refused} refused naming the key, {progressing} still \
         making progress at the cut-off, {} failed",
        all.iter().filter(wanted).count(),
        failures.len()
    );
    assert!(
        failures.is_empty(),
        "failed cases:\n{}",
        failures.join("\n")
    );
}
