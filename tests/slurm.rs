//! `uavmeta reproduce --engine slurm` on a real one-node Slurm cluster: `munged`, `slurmctld`
//! and `slurmd` started here, each with its key, socket, ports, state, spool, pid and log files
//! in a temporary directory (`-f slurm.conf` and `SLURM_CONF` on every command, so nothing reads
//! /etc/slurm). The `--quick` plan runs through it; one dataset job is killed with SIGKILL while
//! its dataset file is being written, the plan is submitted again (only what is not done), and
//! every CSV it writes must be the bytes of a local `--quick` run's.
//!
//! Without the daemons (Debian: slurm-wlm, munge; `make test` installs them) the test skips,
//! saying so, except under `CI=true`, where it fails.

mod support;

use std::net::TcpListener;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};
use std::time::Instant;

use support::{run_dir, wait_until, within, Proc, BIN};

const CONFIG: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/configs/reproduce.toml");
const NODE: &str = "uavnode";
const DAEMONS: [&str; 3] = ["munged", "slurmctld", "slurmd"];
const CLIENTS: [&str; 4] = ["sbatch", "squeue", "sinfo", "scancel"];

/// `program` on PATH or in the sbin directories (where Debian puts the daemons).
fn find(program: &str) -> Option<PathBuf> {
    let path = std::env::var("PATH").unwrap_or_default();
    let dirs = path.split(':').map(PathBuf::from);
    let sbin = ["/usr/sbin", "/sbin", "/usr/local/sbin"].map(PathBuf::from);
    dirs.chain(sbin)
        .map(|d| d.join(program))
        .find(|p| p.is_file())
}

/// The daemons and client commands, or `None` after saying what is missing (failing under
/// `CI=true`).
fn engine() -> Option<Vec<PathBuf>> {
    let missing: Vec<&str> = (DAEMONS.iter().chain(&CLIENTS))
        .copied()
        .filter(|p| find(p).is_none())
        .collect();
    if missing.is_empty() {
        return Some(DAEMONS.iter().map(|d| find(d).unwrap()).collect());
    }
    let why = format!(
        "{} not found: install Slurm and munge (Debian: apt-get install slurm-wlm munge; `make test` does as root)",
        missing.join(", ")
    );
    let ci = std::env::var("CI").is_ok_and(|ci| ci == "true");
    assert!(!ci, "required under CI=true: {why}");
    eprintln!("skipped: {why}");
    None
}

/// A port nobody listens on now.
fn free_port() -> u16 {
    let listener = TcpListener::bind("127.0.0.1:0").expect("bind a port");
    listener.local_addr().unwrap().port()
}

/// A one-node cluster; its daemons and its jobs end when it is dropped, whatever the test did.
struct Cluster {
    dir: tempfile::TempDir,
    conf: PathBuf,
    daemons: Vec<Proc>,
}

impl Cluster {
    fn start(programs: &[PathBuf]) -> Cluster {
        let dir = run_dir("uavmeta-slurm-");
        let d = dir.path().to_path_buf();
        let key = d.join("munge.key");
        write_key(&key);
        let socket = d.join("munge.socket");
        let mut cluster = Cluster {
            conf: d.join("slurm.conf"),
            dir,
            daemons: Vec::new(),
        };
        let arg = |flag: &str, path: &Path| format!("--{flag}={}", path.display());
        let munged = vec![
            "-F".into(),
            "-f".into(),
            arg("key-file", &key),
            arg("socket", &socket),
            arg("pid-file", &d.join("munged.pid")),
            arg("log-file", &d.join("munged.log")),
            arg("seed-file", &d.join("munged.seed")),
        ];
        cluster.spawn(&programs[0], "munged", munged);
        wait_until("munged's socket", within(10), || socket.exists());
        std::fs::write(&cluster.conf, slurm_conf(&d, &socket)).unwrap();
        let conf = cluster.conf.display().to_string();
        let ctld = vec!["-D".into(), "-f".into(), conf.clone()];
        cluster.spawn(&programs[1], "slurmctld", ctld);
        let slurmd = vec!["-D".into(), "-N".into(), NODE.into(), "-f".into(), conf];
        cluster.spawn(&programs[2], "slurmd", slurmd);
        let idle = || {
            let out = cluster.client("sinfo", &["-h", "-N", "-n", NODE, "-o", "%t"]);
            String::from_utf8_lossy(&out.stdout).trim() == "idle"
        };
        if !poll(within(20), idle) {
            panic!("the node never became idle:\n{}", cluster.logs());
        }
        cluster
    }

    fn spawn(&mut self, program: &Path, name: &str, args: Vec<String>) {
        let program = program.display().to_string();
        self.daemons
            .push(Proc::spawn_program(&program, name, &args));
    }

    /// A Slurm client command of this cluster.
    fn client(&self, program: &str, args: &[&str]) -> Output {
        Command::new(program)
            .args(args)
            .env("SLURM_CONF", &self.conf)
            .output()
            .unwrap_or_else(|e| panic!("{program}: {e}"))
    }

    /// `uavmeta reproduce` with `args`, seeing this cluster.
    fn uavmeta(&self, args: &[&str]) -> Output {
        Command::new(BIN)
            .arg("reproduce")
            .args(args)
            .env("SLURM_CONF", &self.conf)
            .output()
            .expect("run uavmeta")
    }

    /// Every job in the queue, as `ID STATE` lines (array tasks one per line).
    fn queue(&self) -> String {
        let out = self.client("squeue", &["-h", "-r", "-o", "%i %T"]);
        String::from_utf8_lossy(&out.stdout).into_owned()
    }

    /// The tails of the daemons' logs and stderr.
    fn logs(&self) -> String {
        let mut s = String::new();
        for name in ["slurmctld.log", "slurmd.log", "munged.log"] {
            let text = std::fs::read_to_string(self.dir.path().join(name)).unwrap_or_default();
            let tail: Vec<&str> = text.lines().rev().take(15).collect();
            s += &format!(
                "--- {name}\n{}\n",
                tail.into_iter().rev().collect::<Vec<_>>().join("\n")
            );
        }
        for d in &self.daemons {
            s += &format!("--- {} stderr\n{}\n", d.name, d.stderr());
        }
        s
    }
}

impl Drop for Cluster {
    /// Cancels every job, waits (bounded) for them to leave the node, then kills the daemons
    /// (`Proc`'s drop: SIGKILL to each one's process group).
    fn drop(&mut self) {
        let _ = Command::new("scancel")
            .args(["--full", "--signal=KILL", "--user=root"])
            .env("SLURM_CONF", &self.conf)
            .output();
        let _ = Command::new("scancel")
            .args(["--user=root"])
            .env("SLURM_CONF", &self.conf)
            .output();
        poll(within(10), || self.queue().trim().is_empty());
        self.daemons.reverse();
        self.daemons.clear();
        // A job process the daemons left behind: found by the test's own directory.
        let dir = self.dir.path().display().to_string();
        for pid in support::child_pids(&[BIN, &dir]) {
            unsafe { libc::kill(pid, libc::SIGKILL) };
        }
    }
}

/// A random munge key of 1024 bytes, readable by its owner only.
fn write_key(path: &Path) {
    use std::io::Read;
    use std::os::unix::fs::PermissionsExt;
    let mut key = vec![0u8; 1024];
    std::fs::File::open("/dev/urandom")
        .and_then(|mut f| f.read_exact(&mut key))
        .expect("read /dev/urandom");
    std::fs::write(path, &key).unwrap();
    std::fs::set_permissions(path, std::fs::Permissions::from_mode(0o400)).unwrap();
}

/// The cluster's config: every file in `d`, ports free now, a unique name, no cgroups and no
/// accounting; the scheduler starts jobs as soon as a CPU is free.
fn slurm_conf(d: &Path, socket: &Path) -> String {
    let host = String::from_utf8(Command::new("hostname").arg("-s").output().unwrap().stdout)
        .unwrap()
        .trim()
        .to_string();
    let cpus = std::thread::available_parallelism().map_or(1, |n| n.get());
    let d = d.display();
    format!(
        "ClusterName=uavmeta{pid}\n\
         SlurmctldHost={host}(127.0.0.1)\n\
         SlurmctldPort={ctld}\nSlurmdPort={slurmd}\n\
         AuthType=auth/munge\nCredType=cred/munge\nAuthInfo=socket={socket}\n\
         SlurmUser=root\nSlurmdUser=root\n\
         StateSaveLocation={d}/state\nSlurmdSpoolDir={d}/spool\n\
         SlurmctldPidFile={d}/slurmctld.pid\nSlurmdPidFile={d}/slurmd.pid\n\
         SlurmctldLogFile={d}/slurmctld.log\nSlurmdLogFile={d}/slurmd.log\n\
         ProctrackType=proctrack/linuxproc\nTaskPlugin=task/none\n\
         JobAcctGatherType=jobacct_gather/none\nAccountingStorageType=accounting_storage/none\n\
         JobCompType=jobcomp/none\nMpiDefault=none\nPlugStackConfig=/dev/null\n\
         SchedulerType=sched/backfill\nSelectType=select/cons_tres\nSelectTypeParameters=CR_CPU\n\
         SchedulerParameters=batch_sched_delay=0,sched_min_interval=0,default_queue_depth=1000\n\
         ReturnToService=2\nKillWait=2\nInactiveLimit=0\nMinJobAge=600\n\
         NodeName={NODE} NodeHostname={host} NodeAddr=127.0.0.1 CPUs={cpus} RealMemory=1000 State=UNKNOWN\n\
         PartitionName=uavmeta Nodes={NODE} Default=YES MaxTime=INFINITE State=UP\n",
        pid = std::process::id(),
        ctld = free_port(),
        slurmd = free_port(),
        socket = socket.display(),
    )
}

/// Polls `done` until it holds (true) or `timeout` passes (false).
fn poll(timeout: std::time::Duration, mut done: impl FnMut() -> bool) -> bool {
    let start = Instant::now();
    while !done() {
        if start.elapsed() > timeout {
            return false;
        }
        std::thread::sleep(std::time::Duration::from_millis(50));
    }
    true
}

fn succeed(what: &str, output: &Output) -> String {
    assert!(
        output.status.success(),
        "{what} failed: {}{}",
        String::from_utf8_lossy(&output.stdout),
        String::from_utf8_lossy(&output.stderr)
    );
    String::from_utf8_lossy(&output.stdout).into_owned()
}

/// Every CSV under `out` but the cache's (whose logs hold wall-clock seconds), by relative path.
fn csvs(out: &Path) -> Vec<(PathBuf, Vec<u8>)> {
    let mut found = Vec::new();
    let mut dirs = vec![out.to_path_buf()];
    while let Some(dir) = dirs.pop() {
        for entry in std::fs::read_dir(&dir).unwrap() {
            let path = entry.unwrap().path();
            let rel = path.strip_prefix(out).unwrap().to_path_buf();
            if path.is_dir() && !rel.starts_with("cache") {
                dirs.push(path);
            } else if path.extension().is_some_and(|e| e == "csv") {
                found.push((rel, std::fs::read(&path).unwrap()));
            }
        }
    }
    found.sort();
    found
}

/// The plan's jobs of `kind`, in array order, as (id, stamp).
fn jobs_of(out: &Path, kind: &str) -> Vec<(String, String)> {
    let plan: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("plan.json")).unwrap()).unwrap();
    let jobs = plan["jobs"].as_array().unwrap();
    jobs.iter()
        .filter(|j| j["kind"] == kind)
        .map(|j| {
            (
                j["id"].as_str().unwrap().into(),
                j["stamp"].as_str().unwrap().into(),
            )
        })
        .collect()
}

fn done(out: &Path, id: &str, stamp: &str) -> bool {
    let marker = out.join("cache/jobs").join(format!("{id}.done"));
    std::fs::read_to_string(marker).is_ok_and(|m| m == stamp)
}

/// The Slurm job id of the latest submission's array of `kind`.
fn array_id(out: &Path, kind: &str) -> String {
    let text = std::fs::read_to_string(out.join("slurm/submitted.json")).unwrap();
    let submitted: serde_json::Value = serde_json::from_str(&text).unwrap();
    let arrays = submitted["arrays"].as_array().unwrap();
    let array = arrays.iter().find(|a| a["kind"] == kind).unwrap();
    array["job_id"].as_str().unwrap().to_string()
}

/// `--status`'s count line: (done, total).
fn status(cluster: &Cluster, out: &Path) -> (usize, usize) {
    let text = succeed(
        "--status",
        &cluster.uavmeta(&["--out", out.to_str().unwrap(), "--status"]),
    );
    let line = text.lines().find(|l| l.starts_with("done ")).expect(&text);
    let words: Vec<&str> = line.split_whitespace().collect();
    (words[1].parse().unwrap(), words[3].parse().unwrap())
}

/// Kills, with SIGKILL, a dataset job whose dataset file exists but whose online agent (saved
/// last) does not yet: the job is writing. Returns the killed job's id and its dataset's path.
fn kill_a_dataset_job_mid_write(cluster: &Cluster, out: &Path) -> (String, PathBuf) {
    let jobs = jobs_of(out, "dataset");
    let array = array_id(out, "dataset");
    let deadline = Instant::now() + within(120);
    loop {
        assert!(
            Instant::now() < deadline,
            "no dataset job was caught writing:\n{}",
            cluster.logs()
        );
        for (index, (id, stamp)) in jobs.iter().enumerate() {
            // dataset/seed-S/TASK -> cache/seed-S/datasets/TASK.uavds
            let (_, rest) = id.split_once('/').unwrap();
            let (seed, task) = rest.split_once('/').unwrap();
            let file = out.join(format!("cache/{seed}/datasets/{task}.uavds"));
            let agent = out.join(format!(
                "cache/{seed}/datasets/{task}.uavds.agent/online-dqn.json"
            ));
            if !file.exists() || agent.exists() || done(out, id, stamp) {
                continue;
            }
            let task_id = format!("{array}_{index}");
            succeed(
                "scancel",
                &cluster.client("scancel", &["--full", "--signal=KILL", &task_id]),
            );
            let gone = || {
                !cluster
                    .queue()
                    .lines()
                    .any(|l| l.starts_with(&format!("{task_id} ")))
            };
            wait_until("the killed job to leave the queue", within(30), gone);
            if !done(out, id, stamp) {
                return (id.clone(), file);
            }
            // It finished before the signal landed: try another.
        }
        std::thread::sleep(std::time::Duration::from_millis(20));
    }
}

#[test]
fn the_quick_plan_through_slurm_survives_a_kill_and_matches_a_local_run() {
    let Some(programs) = engine() else { return };
    let cluster = Cluster::start(&programs);
    // Inside the cluster's directory, so its drop finds any job process left by the path.
    let root = cluster.dir.path();
    let (local, remote) = (root.join("local"), root.join("slurm"));
    let args = |out: &Path| {
        vec![
            "--config".to_string(),
            CONFIG.into(),
            "--quick".into(),
            "--out".into(),
            out.display().to_string(),
        ]
    };

    let started = Instant::now();
    let local_args = args(&local);
    let local_args: Vec<&str> = local_args.iter().map(String::as_str).collect();
    succeed("the local run", &cluster.uavmeta(&local_args));
    let local_time = started.elapsed();

    let started = Instant::now();
    let mut submit = args(&remote);
    submit.extend(["--engine".into(), "slurm".into()]);
    let submit: Vec<&str> = submit.iter().map(String::as_str).collect();
    let first = succeed("the submission", &cluster.uavmeta(&submit));
    assert!(
        first.contains("submitted dataset") && first.contains("squeue -j"),
        "{first}"
    );

    let (killed, file) = kill_a_dataset_job_mid_write(&cluster, &remote);
    assert!(file.exists(), "{}", file.display());
    // The jobs after the killed one's array are cancelled (their dependency failed); the others
    // end by themselves.
    let drained = || cluster.queue().trim().is_empty();
    wait_until(
        "the first submission's jobs to leave the queue",
        within(300),
        drained,
    );
    let (done_before, total) = status(&cluster, &remote);
    assert!(
        done_before < total,
        "{done_before} of {total} done after a kill"
    );

    let again = succeed("the second submission", &cluster.uavmeta(&submit));
    // Only the killed dataset job is collected again.
    let datasets = again.lines().find(|l| l.starts_with("submitted dataset"));
    assert!(datasets.is_some_and(|l| l.ends_with("(1 job)")), "{again}");
    assert!(
        !again.contains("\n0 jobs of the plan were done already"),
        "{again}"
    );
    // --status names the running jobs, from squeue.
    let out_arg = remote.display().to_string();
    let running = || {
        let text = succeed(
            "--status",
            &cluster.uavmeta(&["--out", &out_arg, "--status"]),
        );
        text.lines().any(|l| l.starts_with("  running: "))
    };
    wait_until("--status to show a running job", within(120), running);
    let finished = || {
        // The queue first: once it is empty no job can still mark itself done.
        let queued = !cluster.queue().trim().is_empty();
        let (done, total) = status(&cluster, &remote);
        assert!(
            done == total || queued,
            "the queue is empty with {done} of {total} done:\n{}",
            logs(&remote)
        );
        done == total
    };
    wait_until("every job of the plan", within(900), finished);
    let slurm_time = started.elapsed();

    let (local_csvs, slurm_csvs) = (csvs(&local), csvs(&remote));
    assert!(local_csvs.len() >= 10, "{local_csvs:?}");
    let names = |c: &[(PathBuf, Vec<u8>)]| c.iter().map(|(p, _)| p.clone()).collect::<Vec<_>>();
    assert_eq!(names(&slurm_csvs), names(&local_csvs));
    for ((path, a), (_, b)) in local_csvs.iter().zip(&slurm_csvs) {
        assert!(
            a == b,
            "{} differs between the local and the Slurm run",
            path.display()
        );
    }
    assert!(remote.join("summary.md").exists());
    eprintln!(
        "the quick plan: local {:.1} s, through Slurm {:.1} s (killed {killed} and submitted again)",
        local_time.as_secs_f64(),
        slurm_time.as_secs_f64()
    );
}

/// The jobs' logs, for a failure's message.
fn logs(out: &Path) -> String {
    let dir = out.join("slurm/logs");
    let mut s = String::new();
    for entry in std::fs::read_dir(dir).into_iter().flatten().flatten() {
        let text = std::fs::read_to_string(entry.path()).unwrap_or_default();
        if text.contains("ERROR") || text.contains("error") || text.contains("panicked") {
            s += &format!("--- {}\n{text}\n", entry.path().display());
        }
    }
    s
}

#[test]
fn bad_submissions_are_refused_by_name() {
    let Some(programs) = engine() else { return };
    let cluster = Cluster::start(&programs);
    let out = cluster.dir.path().join("out").display().to_string();
    let refused = |extra: &[&str]| -> String {
        let mut args = vec![
            "--config", CONFIG, "--quick", "--out", &out, "--engine", "slurm",
        ];
        args.extend(extra);
        let output = cluster.uavmeta(&args);
        let stderr = String::from_utf8_lossy(&output.stderr).into_owned();
        assert_eq!(output.status.code(), Some(1), "{stderr}");
        assert!(!stderr.contains("panicked"), "{stderr}");
        stderr
    };
    let stderr = refused(&["--partition", "no-such-partition"]);
    assert!(
        stderr.contains("sbatch") && stderr.contains("nvalid partition"),
        "{stderr}"
    );
    let stderr = refused(&["--time", "1h"]);
    assert!(
        stderr.contains("reproduce.slurm.time") && stderr.contains("\"1h\""),
        "{stderr}"
    );

    // Without sbatch on PATH.
    let output = Command::new(BIN)
        .args([
            "reproduce",
            "--config",
            CONFIG,
            "--quick",
            "--out",
            &out,
            "--engine",
            "slurm",
        ])
        .env("PATH", cluster.dir.path())
        .env("SLURM_CONF", &cluster.conf)
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert_eq!(output.status.code(), Some(1), "{stderr}");
    assert!(
        stderr.contains("`sbatch`") && stderr.contains("PATH"),
        "{stderr}"
    );
}
