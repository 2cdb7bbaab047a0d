//! Remote actor hosts, end to end, on one machine that plays two hosts honestly: host A (the
//! learner's) and host B (actors) run in two iceoryx2 domains (`run.domain`: their own
//! shared-memory prefix and root path), so they cannot see each other's shared memory, and only
//! the tunnel (`uavmeta tunnel serve` / `join`) over a loopback Zenoh link connects them. The
//! launch test checks, from /proc, that B's processes never open anything of A's domain.

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use uavmeta_actors::actor::ActorOptions;
use uavmeta_proto::config::RunConfig;
use uavmeta_proto::metrics;
use uavmeta_proto::transport::{self, RunDir};

mod support;
use support::{dataset_seqs, run_dir, wait_until, within, Proc};

/// Two meta-train tasks (so no meta-learning: the run is done when its datasets are), one local
/// actor per task on host A.
const CONFIG: &str = r#"
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

[collect]
policy = "random"
actors_per_task = 1

[run]
batch_size = 16
"#;

/// The two hosts of one test: domains, directories, the Zenoh endpoint, and A's run.
struct Hosts {
    dir: tempfile::TempDir,
    domain_a: String,
    domain_b: String,
    endpoint: String,
    run_a: RunDir,
}

impl Hosts {
    fn new(name: &str) -> Self {
        let dir = run_dir(&format!("remote-{name}-"));
        let pid = std::process::id();
        // A free loopback port: bound and released; Zenoh binds it a moment later.
        let port = std::net::TcpListener::bind("127.0.0.1:0")
            .and_then(|l| l.local_addr())
            .expect("a free port")
            .port();
        let run_a = RunDir::create(&dir.path().join("host-a-run")).expect("run dir");
        Hosts {
            domain_a: format!("{name}a{pid}"),
            domain_b: format!("{name}b{pid}"),
            endpoint: format!("tcp/127.0.0.1:{port}"),
            run_a,
            dir,
        }
    }

    fn path(&self) -> &Path {
        self.dir.path()
    }

    fn dir_b(&self) -> PathBuf {
        self.path().join("host-b-run")
    }

    /// `--config` and `--set`s of host A.
    fn config_args(&self, extra: &[String]) -> Vec<String> {
        let config = self.path().join("config.toml");
        std::fs::write(&config, CONFIG).expect("config");
        let mut args = vec!["--config".to_string(), config.display().to_string()];
        let sets = [
            format!("run.dir={}", self.run_a.root().display()),
            format!("run.domain={}", self.domain_a),
            format!("tunnel.listen={}", self.endpoint),
        ];
        for set in sets.iter().chain(extra) {
            args.extend(["--set".to_string(), set.clone()]);
        }
        args
    }

    fn join(&self, run_id: &str) -> Proc {
        let args = [
            "tunnel",
            "join",
            "--connect",
            &self.endpoint,
            "--run-id",
            run_id,
            "--dir",
            &self.dir_b().display().to_string(),
            "--domain",
            &self.domain_b,
            "--host",
            "hostb",
        ];
        Proc::spawn("join", &strings(&args))
    }

    /// An actor on host B, once `join` has made B's directory for the run.
    fn actor_b(&self, task: &str, extra: &[&str]) -> Proc {
        let config = self.dir_b().join("config.toml");
        wait_until("host B's run directory", within(60), || config.exists());
        let mut args = strings(&[
            "actor",
            "--run",
            &self.dir_b().display().to_string(),
            "--task",
            task,
            "--seed",
            "100",
            "--policy",
            "random",
        ]);
        args.extend(strings(extra));
        Proc::spawn(&format!("actor-b-{task}"), &args)
    }
}

/// Removes both domains' iceoryx2 files. Fields drop after this, so the processes (owned by
/// the test function, dropped first) are gone by then.
impl Drop for Hosts {
    fn drop(&mut self) {
        for domain in [&self.domain_a, &self.domain_b] {
            let run = RunConfig {
                domain: domain.clone(),
                ..RunConfig::default()
            };
            if let Err(error) = transport::remove_domain(&run) {
                eprintln!("{error}");
            }
        }
    }
}

fn strings(args: &[&str]) -> Vec<String> {
    args.iter().map(|s| s.to_string()).collect()
}

/// B's actor of `task`'s id, which its batches carry.
fn b_actor_id(task: &str) -> u32 {
    ActorOptions {
        task: task.into(),
        policy: "random".parse().expect("policy"),
        seed: 100,
        transitions: None,
    }
    .actor_id()
}

/// What some processes' /proc/PID/maps and /proc/PID/fd showed, sampled until stopped.
#[derive(Default, Debug)]
struct Seen {
    /// Paths of the other domain a process had mapped or open: must stay empty.
    foreign: Vec<String>,
    /// Whether a process had its own domain's shared memory mapped or open (the check works).
    own: bool,
}

/// Samples the iceoryx2 files of `pids` every few milliseconds in a thread, until the returned
/// flag is set.
fn watch_domains(
    pids: Arc<Mutex<Vec<i32>>>,
    own: String,
    foreign: String,
) -> (Arc<AtomicBool>, std::thread::JoinHandle<Seen>) {
    let stop = Arc::new(AtomicBool::new(false));
    let flag = stop.clone();
    let handle = std::thread::spawn(move || {
        let mut seen = Seen::default();
        while !flag.load(Ordering::Relaxed) {
            for pid in pids.lock().expect("pids").clone() {
                for path in iceoryx_files(pid) {
                    if in_domain(&path, &foreign) {
                        seen.foreign.push(format!("pid {pid}: {path}"));
                    } else if in_domain(&path, &own) {
                        seen.own = true;
                    }
                }
            }
            std::thread::sleep(Duration::from_millis(5));
        }
        seen
    });
    (stop, handle)
}

fn in_domain(path: &str, domain: &str) -> bool {
    path.contains(&format!("/iox2_{domain}_")) || path.contains(&format!("/iceoryx2/{domain}/"))
}

/// The paths a process has mapped or open.
fn iceoryx_files(pid: i32) -> Vec<String> {
    let maps = std::fs::read_to_string(format!("/proc/{pid}/maps")).unwrap_or_default();
    let mut paths: Vec<String> = maps
        .lines()
        .filter_map(|l| l.split_whitespace().nth(5).map(str::to_string))
        .collect();
    if let Ok(fds) = std::fs::read_dir(format!("/proc/{pid}/fd")) {
        paths.extend(
            fds.flatten()
                .filter_map(|fd| std::fs::read_link(fd.path()).ok())
                .map(|p| p.display().to_string()),
        );
    }
    paths
}

fn final_metrics(run: &Path, process: &str) -> Vec<metrics::Sample> {
    let path = run.join("metrics").join(format!("{process}.prom"));
    let text = std::fs::read_to_string(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    metrics::parse(&text).expect("metrics")
}

#[test]
fn a_launch_with_two_local_and_two_remote_actors_stores_the_remote_transitions() {
    let hosts = Hosts::new("e2e");
    let tasks = ["lambda-0", "lambda-100"];
    let mut args = strings(&["launch"]);
    args.extend(hosts.config_args(&[
        "collect.transitions=300000".into(),
        "tunnel.wait_for_hosts=[\"hostb\"]".into(),
    ]));
    let mut launch = Proc::spawn("launch", &args);
    let join = hosts.join(hosts.run_a.id());
    let actors: Vec<Proc> = tasks.iter().map(|t| hosts.actor_b(t, &[])).collect();
    let pids_b = Arc::new(Mutex::new(
        actors.iter().chain([&join]).map(Proc::pid).collect(),
    ));
    let (stop, watcher) = watch_domains(pids_b, hosts.domain_b.clone(), hosts.domain_a.clone());
    let targets_file = hosts.run_a.root().join("prometheus-targets.json");
    let mut remote_targets = false;
    wait_until("the launch to finish", within(240), || {
        let targets = std::fs::read_to_string(&targets_file).unwrap_or_default();
        remote_targets |= targets.contains("\"host\": \"hostb\"") && targets.contains("actor-");
        !launch.running()
    });
    let launch_log = launch.succeeds(Duration::ZERO).stderr;
    for actor in actors {
        actor.succeeds(within(60));
    }
    join.succeeds(within(60));
    stop.store(true, Ordering::Relaxed);
    let seen = watcher.join().expect("watcher");
    assert!(
        seen.foreign.is_empty(),
        "host B touched host A's domain: {:?}",
        seen.foreign
    );
    assert!(
        seen.own,
        "host B's processes never showed their own iceoryx2 files: the check is blind"
    );
    assert!(
        remote_targets,
        "host B's actors never appeared in prometheus-targets.json"
    );

    let seqs = dataset_seqs(hosts.run_a.root());
    let store = final_metrics(hosts.run_a.root(), "store");
    for task in tasks {
        let per_actor = &seqs[task];
        let remote = per_actor.get(&b_actor_id(task)).map_or(0, Vec::len);
        assert!(
            remote > 0,
            "{task}: none of host B's transitions in host A's dataset"
        );
        assert_eq!(
            per_actor.values().map(Vec::len).sum::<usize>(),
            300_000,
            "{task}"
        );
        let counted = metrics::sum(
            &store,
            metrics::store::DATASET_TRANSITIONS,
            &[("task", task)],
        );
        assert_eq!(counted, 300_000.0, "{task}: the store's count");
    }
    assert!(
        launch_log.contains("remote actor host host=hostb"),
        "{launch_log}"
    );
    assert!(
        launch_log.contains(&format!("--run-id {}`", hosts.run_a.id())),
        "the launcher names the run id to join: {launch_log}"
    );
}

/// A store and a tunnel started by hand on host A (no launcher, so nothing restarts the tunnel
/// but the test), once both serve.
fn start_host_a(hosts: &Hosts, extra: &[String]) -> (Proc, Proc) {
    let run = hosts.run_a.root().display().to_string();
    let mut args = strings(&["store", "--run", &run]);
    args.extend(hosts.config_args(extra));
    let store = Proc::spawn("store", &args);
    let port = hosts.run_a.port_file("store");
    wait_until("the store", within(60), || port.exists());
    (store, start_tunnel(hosts, "tunnel"))
}

fn start_tunnel(hosts: &Hosts, name: &str) -> Proc {
    let run = hosts.run_a.root().display().to_string();
    let mut tunnel = Proc::spawn(name, &strings(&["tunnel", "serve", "--run", &run]));
    tunnel.logs("serving the run", within(60));
    tunnel
}

/// The live store's count of stored transitions: only host B's actor publishes in the test.
fn stored(run: &RunDir) -> f64 {
    std::fs::read_to_string(run.port_file("store"))
        .ok()
        .and_then(|port| metrics::scrape("127.0.0.1", port.trim().parse().ok()?).ok())
        .and_then(|text| metrics::parse(&text).ok())
        .map_or(0.0, |samples| {
            metrics::sum(&samples, metrics::store::TRANSITIONS_STORED, &[])
        })
}

/// Accounting across the tunnel: the learner host's tunnel is killed (SIGKILL) while a remote
/// actor publishes, and restarted; the actor resumes, and every number it published is stored or
/// counted missing by the store.
#[test]
fn a_killed_and_restarted_tunnel_loses_nothing_unaccounted_and_the_remote_actor_resumes() {
    const PUBLISHED: u64 = 1_000_000;
    let hosts = Hosts::new("kill");
    let (store, tunnel) = start_host_a(&hosts, &["collect.transitions=10000000".into()]);
    let mut join = hosts.join(hosts.run_a.id());
    let task = "lambda-0";
    let transitions = PUBLISHED.to_string();
    let mut actor = hosts.actor_b(task, &["--transitions", &transitions]);
    let actor_id = b_actor_id(task);
    let run = hosts.run_a.root();
    wait_until(
        "host B's first transitions in the store",
        within(120),
        || stored(&hosts.run_a) > 0.0,
    );
    assert!(
        actor.running(),
        "the remote actor finished before the tunnel was killed"
    );
    tunnel.signal(libc::SIGKILL);
    tunnel.wait(within(10));
    let at_kill = stored(&hosts.run_a) as usize;
    join.logs("lost the run's tunnel", within(60));
    let _tunnel = start_tunnel(&hosts, "tunnel-restarted");
    actor.succeeds(within(240));
    // SIGTERM: the store syncs and writes its final metrics.
    store.signal(libc::SIGTERM);
    store.succeeds(within(60));
    drop(join);

    let seqs = &dataset_seqs(run)[task][&actor_id];
    let missing_in_file = seqs.last().map_or(0, |last| last + 1) - seqs.len() as u64;
    let counted = metrics::sum(
        &final_metrics(run, "store"),
        metrics::store::TRANSITIONS_MISSING,
        &[("task", task)],
    );
    let published = metrics::sum(
        &final_metrics(&hosts.dir_b(), &format!("actor-{task}-{actor_id:08x}")),
        metrics::actor::TRANSITIONS_PUBLISHED,
        &[],
    );
    assert_eq!(published, PUBLISHED as f64);
    assert_eq!(
        missing_in_file as f64, counted,
        "missing in the file vs the store's count"
    );
    assert_eq!(
        seqs.len() as u64 + missing_in_file,
        PUBLISHED,
        "published = stored + counted missing"
    );
    assert!(
        seqs.len() > at_kill,
        "nothing stored after the restart: the actor did not resume"
    );
    // Not zero in general: a batch the tunnel drops is a gap (docs in tunnel/src/lib.rs).
    eprintln!(
        "published {published}, stored {}, counted missing {counted}",
        seqs.len()
    );
}

/// Bad input gets clear errors: an unreachable endpoint (retried with backoff, named), a run the
/// learner's host does not serve (its runs named).
#[test]
fn joining_an_unreachable_endpoint_or_an_unknown_run_fails_with_a_message_naming_it() {
    let hosts = Hosts::new("bad");
    let unreachable = Proc::spawn(
        "unreachable",
        &strings(&[
            "tunnel",
            "join",
            "--connect",
            &hosts.endpoint,
            "--run-id",
            "nothing-0",
            "--dir",
            &hosts.dir_b().display().to_string(),
            "--domain",
            &hosts.domain_b,
            "--patience",
            "2",
        ]),
    );
    let out = unreachable.wait(within(60)).stderr;
    assert!(!out.is_empty() && out.contains("trying again"), "{out}");
    assert!(
        out.contains(&format!(
            "cannot reach the run's tunnel at `{}`",
            hosts.endpoint
        )),
        "{out}"
    );

    let (_store, _tunnel) = start_host_a(&hosts, &[]);
    let unknown = Proc::spawn(
        "unknown",
        &strings(&[
            "tunnel",
            "join",
            "--connect",
            &hosts.endpoint,
            "--run-id",
            "no-such-run",
            "--dir",
            &hosts.dir_b().display().to_string(),
            "--domain",
            &hosts.domain_b,
        ]),
    );
    let out = unknown.wait(within(60)).stderr;
    assert!(out.contains("serves no run `no-such-run`"), "{out}");
    assert!(
        out.contains(hosts.run_a.id()),
        "the served run is named: {out}"
    );
}
