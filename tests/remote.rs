//! Remote actor hosts, end to end, on one machine that plays two hosts honestly: host A (the
//! learner's) and host B (actors) run in two iceoryx2 domains (`run.domain`: their own
//! shared-memory prefix and root path), so they cannot see each other's shared memory, and only
//! the tunnel (`uavmeta tunnel serve` / `join`) over a loopback Zenoh link connects them. The
//! launch test checks, from /proc, that B's processes never open anything of A's domain.

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use uavmeta_proto::config::Config;
use uavmeta_proto::config::RunConfig;
use uavmeta_proto::dataset::DatasetReader;
use uavmeta_proto::metrics;
use uavmeta_proto::payload::ServiceNames;
use uavmeta_runtime::actor::ActorOptions;
use uavmeta_runtime::metrics::{parse, scrape, sum, Sample};
use uavmeta_runtime::run_dir::RunDir;
use uavmeta_runtime::{domain, transport};

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
transitions_per_message = 16

[tunnel.hosts]
hostb = ["*"]
"#;

/// The two hosts of one test: domains, directories, the Zenoh endpoint, and A's run. The tunnel
/// runs as a real deployment would: mutual TLS with certificates made by `uavmeta tunnel certs`
/// for this test, and a password on top.
struct Hosts {
    dir: tempfile::TempDir,
    domain_a: String,
    domain_b: String,
    endpoint: String,
    run_a: RunDir,
}

/// `uavmeta tunnel certs` for `host` in `dir` (the CA is made by the first call).
fn certs(dir: &Path, host: &str) {
    let dir = dir.display().to_string();
    let args = [
        "tunnel",
        "certs",
        "--dir",
        &dir,
        "--host",
        host,
        "--address",
        "127.0.0.1",
    ];
    Proc::spawn("certs", &strings(&args)).succeeds(within(60));
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
        let tls = dir.path().join("tls");
        certs(&tls, "learner");
        certs(&tls, "hostb");
        certs(&tls, "hostc");
        certs(&tls, "hostd");
        std::fs::write(
            tls.join("passwords"),
            "hostb:correct-horse\nhostc:battery-staple\nhostd:tr0ub4dor\n",
        )
        .expect("dictionary");
        for (host, password) in [("hostc", "battery-staple"), ("hostd", "tr0ub4dor")] {
            let line = format!("{host}:{password}\n");
            std::fs::write(tls.join(format!("{host}.credentials")), line).expect("credentials");
        }
        std::fs::write(tls.join("hostb.credentials"), "hostb:correct-horse\n")
            .expect("credentials");
        Hosts {
            domain_a: format!("{name}a{pid}"),
            domain_b: format!("{name}b{pid}"),
            endpoint: format!("tls/127.0.0.1:{port}"),
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

    fn tls(&self, file: &str) -> String {
        self.path().join("tls").join(file).display().to_string()
    }

    /// `join`'s flags that admit host B: its certificate, key and password, and the run's CA.
    fn b_credentials(&self) -> Vec<String> {
        join_flags(
            &self.tls("ca.pem"),
            &self.tls("hostb.pem"),
            &self.tls("hostb.key"),
            &self.tls("hostb.credentials"),
        )
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
            format!("tunnel.ca={}", self.tls("ca.pem")),
            format!("tunnel.certificate={}", self.tls("learner.pem")),
            format!("tunnel.private_key={}", self.tls("learner.key")),
            format!("tunnel.credentials={}", self.tls("passwords")),
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
        let mut args = strings(&args);
        args.extend(self.b_credentials());
        Proc::spawn("join", &args)
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
            if let Err(error) = domain::remove_domain(&run) {
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

fn final_metrics(run: &Path, process: &str) -> Vec<Sample> {
    let path = run.join("metrics").join(format!("{process}.prom"));
    let text = std::fs::read_to_string(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    parse(&text).expect("metrics")
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
        let reader = dataset_a(&hosts, task);
        let made: Vec<(&str, u64)> = reader.provenance().into_iter().collect();
        let remote = made
            .iter()
            .find(|(host, _)| *host == "hostb")
            .map_or(0, |m| m.1);
        assert!(
            made.len() == 2 && remote > 0 && remote <= 150_000,
            "{task}: made by {made:?}: both hosts, host B at most tunnel.max_host_share"
        );
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
        let counted = sum(
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
        .and_then(|port| scrape("127.0.0.1", port.trim().parse().ok()?).ok())
        .and_then(|text| parse(&text).ok())
        .map_or(0.0, |samples| {
            sum(&samples, metrics::store::TRANSITIONS_STORED, &[])
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
    let counted = sum(
        &final_metrics(run, "store"),
        metrics::store::TRANSITIONS_MISSING,
        &[("task", task)],
    );
    let published = sum(
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

/// `tunnel join` of host B to `run_id` with `credentials`, given up after 3 s: its stderr.
fn refused_join(hosts: &Hosts, endpoint: &str, run_id: &str, credentials: &[String]) -> String {
    let dir_b = hosts.dir_b().display().to_string();
    let mut args = strings(&[
        "tunnel",
        "join",
        "--connect",
        endpoint,
        "--run-id",
        run_id,
        "--dir",
        &dir_b,
        "--domain",
        &hosts.domain_b,
        "--host",
        "hostb",
        "--patience",
        "3",
    ]);
    args.extend(credentials.iter().cloned());
    let out = Proc::spawn("refused", &args).wait(within(120));
    assert!(
        !out.status.success(),
        "joined with {credentials:?}: {}",
        out.stderr
    );
    assert!(
        !hosts.dir_b().join("config.toml").exists(),
        "{credentials:?} got the config"
    );
    out.stderr
}

/// `tunnel join`'s credential flags: the CA to trust, the host's certificate and key, and its
/// `user:password` file.
fn join_flags(ca: &str, certificate: &str, private_key: &str, credentials: &str) -> Vec<String> {
    strings(&[
        "--ca",
        ca,
        "--certificate",
        certificate,
        "--private-key",
        private_key,
        "--credentials",
        credentials,
    ])
}

/// Bad input and strangers get one clear error that reveals nothing of the runs served: an
/// unreachable endpoint, a run id not served, no certificate, another CA's certificate, a wrong
/// password; and plain TCP beyond loopback is refused on both sides.
#[test]
fn a_stranger_is_refused_with_one_error_that_names_no_run() {
    let hosts = Hosts::new("bad");
    let admitted = hosts.b_credentials();
    let unreachable = refused_join(&hosts, &hosts.endpoint, hosts.run_a.id(), &admitted);
    assert!(unreachable.contains("trying again"), "{unreachable}");

    let (_store, _tunnel) = start_host_a(&hosts, &[]);
    let another_ca = hosts.path().join("other-ca");
    certs(&another_ca, "hostb");
    let other = |file: &str| another_ca.join(file).display().to_string();
    let wrong_password = hosts.path().join("wrong.credentials");
    std::fs::write(&wrong_password, "hostb:guess\n").expect("credentials");
    let plain = hosts.endpoint.replace("tls/", "tcp/");
    let tls = hosts.endpoint.as_str();
    let no_password = admitted[..6].to_vec();
    let cases: Vec<(&str, &str, &str, Vec<String>)> = vec![
        ("a run id not served", tls, "no-such-run", admitted.clone()),
        (
            "no certificate (plain TCP)",
            &plain,
            hosts.run_a.id(),
            vec![],
        ),
        ("no password", tls, hosts.run_a.id(), no_password),
        (
            "another CA's certificate",
            tls,
            hosts.run_a.id(),
            join_flags(
                &hosts.tls("ca.pem"),
                &other("hostb.pem"),
                &other("hostb.key"),
                &hosts.tls("hostb.credentials"),
            ),
        ),
        (
            "a wrong password",
            tls,
            hosts.run_a.id(),
            join_flags(
                &hosts.tls("ca.pem"),
                &hosts.tls("hostb.pem"),
                &hosts.tls("hostb.key"),
                &wrong_password.display().to_string(),
            ),
        ),
    ];
    for (what, endpoint, run_id, credentials) in cases {
        let out = refused_join(&hosts, endpoint, run_id, &credentials);
        let expected = format!("cannot join run `{run_id}` at `{endpoint}`");
        assert!(out.contains(&expected), "{what}: {out}");
        assert!(
            !out.contains(hosts.run_a.id()) || run_id == hosts.run_a.id(),
            "{what} named the served run: {out}"
        );
    }

    // Plain TCP beyond loopback: refused before any connection, on either side.
    let plain = Proc::spawn(
        "plain-join",
        &strings(&[
            "tunnel",
            "join",
            "--connect",
            "tcp/10.0.0.1:7447",
            "--run-id",
            "r",
            "--dir",
            &hosts.dir_b().display().to_string(),
        ]),
    )
    .wait(within(60));
    assert!(
        !plain.status.success() && plain.stderr.contains("needs a tls/ endpoint"),
        "{}",
        plain.stderr
    );
    let mut args = strings(&[
        "tunnel",
        "serve",
        "--run",
        &hosts.path().join("plain").display().to_string(),
    ]);
    args.extend(hosts.config_args(&[]));
    args.extend(strings(&["--set", "tunnel.listen=tcp/0.0.0.0:7447"]));
    let serve = Proc::spawn("plain-serve", &args).wait(within(60));
    assert!(
        !serve.status.success() && serve.stderr.contains("tunnel certs"),
        "{}",
        serve.stderr
    );
}

/// Publishes `message` into `service` of host B's domain, as a hostile remote host can.
fn forge<T: std::fmt::Debug + iceoryx2::prelude::ZeroCopySend + Copy + 'static>(
    node: &iceoryx2::node::Node<iceoryx2::prelude::ipc::Service>,
    config: &uavmeta_proto::config::Config,
    service: String,
    message: T,
) {
    let service = transport::control_service::<T>(node, service, config).expect("service");
    let publisher = transport::control_publisher(&service).expect("publisher");
    transport::announce(&publisher, message).expect("announce");
}

/// Least privilege across the tunnel: a remote host that publishes a Shutdown and a
/// DatasetReady, into its own services and into the copies that cross, reaches no process of the
/// learner's host, whose store keeps storing what the remote actor sends.
#[test]
fn a_remote_hosts_forged_shutdown_and_dataset_ready_reach_nothing_on_the_learners_host() {
    use uavmeta_proto::payload::{DatasetReady, Shutdown, SCHEMA_VERSION};
    let hosts = Hosts::new("forge");
    let (mut store, mut tunnel) = start_host_a(&hosts, &["collect.transitions=10000000".into()]);
    let mut join = hosts.join(hosts.run_a.id());
    let config_b = hosts.dir_b().join("config.toml");
    wait_until("host B's run directory", within(60), || config_b.exists());
    join.logs("bridging the run's services", within(60));
    let config = Config::load(&config_b, &[]).expect("B's config");
    let names = ServiceNames::new(RunDir::open(&hosts.dir_b()).expect("B's run").id());
    let node = domain::node("forger", &config.run).expect("a node in B's domain");
    let shutdown = Shutdown {
        schema_version: SCHEMA_VERSION,
        reserved: 0,
    };
    let ready = DatasetReady {
        schema_version: SCHEMA_VERSION,
        task: 0,
        transitions: 10_000_000,
    };
    for service in [names.shutdown(), names.to_remote(&names.shutdown())] {
        forge(&node, &config, service, shutdown);
    }
    for service in [
        names.dataset_ready(),
        names.to_remote(&names.dataset_ready()),
    ] {
        forge(&node, &config, service, ready);
    }
    // A remote actor publishes after the forgeries: the tunnel carries, and A's store takes it.
    let actor = hosts.actor_b("lambda-0", &["--transitions", "2000"]);
    wait_until("host B's transitions in A's store", within(120), || {
        stored(&hosts.run_a) >= 2000.0
    });
    drop(actor);
    assert!(
        store.running() && tunnel.running(),
        "a forged message stopped host A's processes"
    );
    // A's own services keep what was announced in their history: nothing.
    let config_a = Config::load(&hosts.run_a.config_file(), &[]).expect("A's config");
    let node_a = domain::node("witness", &config_a.run).expect("a node in A's domain");
    let names_a = ServiceNames::new(hosts.run_a.id());
    let heard = |service: String| -> usize {
        let service =
            transport::control_service::<Shutdown>(&node_a, service, &config_a).expect("service");
        let subscriber = transport::control_subscriber(&service).expect("subscriber");
        std::iter::from_fn(|| subscriber.receive().expect("receive")).count()
    };
    assert_eq!(
        heard(names_a.shutdown()),
        0,
        "a forged Shutdown reached host A"
    );
    let ready_service =
        transport::dataset_ready_service(&node_a, &names_a, &config_a).expect("service");
    let subscriber = transport::control_subscriber(&ready_service).expect("subscriber");
    let announced = std::iter::from_fn(|| subscriber.receive().expect("receive")).count();
    assert_eq!(announced, 0, "a forged DatasetReady reached host A");
}

/// A Zenoh session admitted as host B (its certificate and password), as a hostile or buggy
/// remote host holds one: the project's own `session::connect`.
fn rogue_session(hosts: &Hosts) -> zenoh::Session {
    session_as(hosts, "hostb")
}

/// A Zenoh session admitted as `host`.
fn session_as(hosts: &Hosts, host: &str) -> zenoh::Session {
    let file = |ext: &str| Some(hosts.tls(&format!("{host}.{ext}")).into());
    let security = uavmeta_tunnel::Security {
        ca: Some(hosts.tls("ca.pem").into()),
        certificate: file("pem"),
        private_key: file("key"),
        credentials: file("credentials"),
    };
    let mut session = None;
    // The tunnel may still be starting: a client's session fails to open until it listens.
    wait_until("an admitted session", within(60), || {
        session = uavmeta_tunnel::session::connect(&hosts.endpoint, &security).ok();
        session.is_some()
    });
    session.expect("connected")
}

/// The handshake's answers to a query of `key` within a few seconds (a Hello as `join` sends).
fn handshake_answers(session: &zenoh::Session, key: &str) -> usize {
    use zenoh::Wait;
    let hello = br#"{"schema_version":0,"host":"hostb"}"#.to_vec();
    let replies = session
        .get(key)
        .payload(hello)
        .timeout(Duration::from_secs(3))
        .wait()
        .expect("query");
    std::iter::from_fn(|| replies.recv().ok()).count()
}

/// Issue #61: `--run-id '*'` admits nothing. `join` refuses a run id that is not one (a Zenoh
/// wildcard above all) before it connects, and the learner host's tunnel answers only a
/// handshake that names its run: an admitted session's wildcard query gets no answer, and its
/// wildcard liveliness query lists no run (docs/SECURITY.md).
#[test]
fn a_wildcard_run_id_admits_nothing_and_learns_no_run() {
    use zenoh::Wait;
    let hosts = Hosts::new("wild");
    let (_store, _tunnel) = start_host_a(&hosts, &[]);
    for id in ["*", "**", "$*", "a/b"] {
        let refused = refused_join(&hosts, &hosts.endpoint, id, &hosts.b_credentials());
        assert!(
            refused.contains(&format!("--run-id `{id}`")) && !refused.contains(hosts.run_a.id()),
            "{id}: {refused}"
        );
    }
    let rogue = rogue_session(&hosts);
    let run_key = uavmeta_tunnel::session::run_key(hosts.run_a.id());
    // The exact key is answered (with a refusal of the schema version 0): the check is not blind.
    wait_until("the tunnel to answer its run's key", within(60), || {
        handshake_answers(&rogue, &run_key) > 0
    });
    for wildcard in ["uavmeta/runs/*", "uavmeta/**", "uavmeta/runs/host-a$*"] {
        assert_eq!(
            handshake_answers(&rogue, wildcard),
            0,
            "{wildcard} was answered"
        );
    }
    // docs/SECURITY.md: the tunnel's access control lets an admitted host ask only for its run's
    // own keys, so a wildcard query of the liveliness tokens lists no run, while the run's own
    // key finds its token (the check is not blind).
    let tokens = |key: &str| -> Vec<String> {
        let replies = (rogue.liveliness().get(key))
            .timeout(Duration::from_secs(3))
            .wait()
            .expect("liveliness query");
        std::iter::from_fn(|| replies.recv().ok())
            .filter_map(|reply| reply.result().ok().map(|s| s.key_expr().to_string()))
            .collect()
    };
    assert_eq!(
        tokens(&run_key),
        std::slice::from_ref(&run_key),
        "the run's own token"
    );
    let keys = tokens("uavmeta/runs/*");
    assert!(
        keys.is_empty(),
        "an admitted host listed the runs: {keys:?}"
    );
}

/// An announcement as a remote host's `join` sends it: `processes` names at `address`, each with
/// its own port from `first_port` on.
fn announcement(host: &str, address: &str, processes: usize, first_port: u16) -> Vec<u8> {
    let processes: Vec<uavmeta_runtime::run_dir::RemoteProcess> = (0..processes)
        .map(|i| uavmeta_runtime::run_dir::RemoteProcess {
            name: format!("actor-lambda-0-{i:08x}"),
            metrics: format!("{address}:{}", first_port + i as u16),
        })
        .collect();
    let host = uavmeta_runtime::run_dir::RemoteHost {
        host: host.into(),
        processes,
    };
    serde_json::to_vec(&host).expect("serialises")
}

/// Issue #61: an admitted host's announcements can neither point the learner's Prometheus
/// elsewhere nor flood the launcher's log. Host B (certificate `hostb`) announces, ten times a
/// second for five seconds, 253 processes at the learner's loopback with ports that change
/// every time, and the same under the name `evil`: the targets list `hostb`'s processes only
/// at the address B reaches the tunnel from (with the ports B named), nothing of `evil`, and the
/// launcher logs B once.
#[test]
fn a_remote_hosts_announcements_cannot_redirect_the_scrapes_or_flood_the_log() {
    use zenoh::Wait;
    let hosts = Hosts::new("announce");
    let mut args = strings(&["launch"]);
    args.extend(hosts.config_args(&[
        "tunnel.wait_for_hosts=[\"hostb\"]".into(),
        "tunnel.wait_seconds=60".into(),
    ]));
    let mut launch = Proc::spawn("launch", &args);
    launch.logs("remote actor hosts join with", within(120));
    let rogue = rogue_session(&hosts);
    let key = |host: &str| format!("uavmeta/runs/{}/hosts/{host}", hosts.run_a.id());
    for round in 0..50u16 {
        for (host, address) in [("hostb", "10.9.9.9"), ("evil", "127.0.0.1")] {
            let payload = announcement(host, address, 253, 1000 + round);
            rogue.put(key(host), payload).wait().expect("put");
        }
        std::thread::sleep(Duration::from_millis(100));
    }
    let targets_file = hosts.run_a.root().join("prometheus-targets.json");
    let read_targets = || -> Vec<serde_json::Value> {
        let text = std::fs::read_to_string(&targets_file).unwrap_or_default();
        serde_json::from_str(&text).unwrap_or_default()
    };
    let of_host = |targets: &[serde_json::Value], host: &str| -> Vec<String> {
        (targets.iter())
            .filter(|t| t["labels"]["host"] == host)
            .map(|t| t["targets"][0].as_str().expect("a target").to_string())
            .collect()
    };
    wait_until("host B's targets", within(60), || {
        !of_host(&read_targets(), "hostb").is_empty()
    });
    let targets = read_targets();
    let b = of_host(&targets, "hostb");
    let evil = of_host(&targets, "evil");
    assert!(
        evil.is_empty(),
        "{} targets of `evil`: {:?}",
        evil.len(),
        &evil[..1]
    );
    assert_eq!(b.len(), 253, "{b:?}");
    let elsewhere: Vec<&String> = b.iter().filter(|t| !t.starts_with("127.0.0.1:")).collect();
    assert!(
        elsewhere.is_empty(),
        "{} of B's targets elsewhere: {:?}",
        elsewhere.len(),
        &elsewhere[..1]
    );
    launch.signal(libc::SIGTERM);
    let log = launch.wait(within(120)).stderr;
    let lines = log
        .lines()
        .filter(|l| l.contains("remote actor host host="))
        .count();
    assert_eq!(lines, 1, "{log}");
}

/// A task's dataset file on host A, read.
fn dataset_a(hosts: &Hosts, task: &str) -> DatasetReader {
    let file = hosts
        .run_a
        .root()
        .join("datasets")
        .join(format!("{task}.uavds"));
    DatasetReader::open(&file).unwrap_or_else(|e| panic!("{e}"))
}

/// The Zenoh key of the frames of `task`'s transitions under `names` (opened in host A's
/// domain, where the store made them): what the tunnel's access control lets one host put on.
fn channel_of(hosts: &Hosts, names: &ServiceNames, task: &str) -> String {
    use iceoryx2::prelude::PortFactory;
    let config = Config::load(&hosts.run_a.config_file(), &[]).expect("A's config");
    let node = domain::node("hasher", &config.run).expect("a node in A's domain");
    let service = transport::transition_service(&node, names, task, &config.run).expect("service");
    format!(
        "iox2/v1/channel/{}/fingerprint",
        service.service_hash().as_str()
    )
}

/// Issue #61: a remote host publishes only under its own name. Host B may serve `lambda-0`,
/// host C `lambda-100`; host D has a certificate of the run's CA and a password, but is not in
/// `tunnel.hosts`: its handshake is not even answered.
/// - Over Zenoh, B's admitted session puts on the channels of A's own actors, of C's services
///   and on C's announcement key: a session of C that subscribes to everything hears none of it,
///   only what B puts on its own channel and key (so the check is not blind).
/// - B's actor of `lambda-100` is refused, naming tunnel.hosts.
/// - B's actor of `lambda-0` publishes 2000 transitions under the id of an actor of A (same
///   task, policy and seed) before A's own starts: both are stored, B's only up to
///   tunnel.max_host_share (half of 3000), and the dataset records who made what.
#[test]
fn a_remote_host_publishes_only_under_its_own_name_and_never_completes_a_dataset_alone() {
    use zenoh::Wait;
    let hosts = Hosts::new("own");
    let served = r#"tunnel.hosts={hostb=["lambda-0"], hostc=["lambda-100"]}"#;
    let (store, _tunnel) =
        start_host_a(&hosts, &["collect.transitions=3000".into(), served.into()]);
    let names = ServiceNames::new(hosts.run_a.id());
    let own = channel_of(&hosts, &names.for_host("hostb"), "lambda-0");
    let forbidden = [
        channel_of(&hosts, &names, "lambda-0"),
        channel_of(&hosts, &names, "lambda-100"),
        channel_of(&hosts, &names.for_host("hostc"), "lambda-100"),
    ];
    let announce = |host: &str| format!("uavmeta/runs/{}/hosts/{host}", hosts.run_a.id());
    let observer = session_as(&hosts, "hostc");
    let heard = Arc::new(Mutex::new(Vec::<String>::new()));
    let mut subscribers = Vec::new();
    for key in ["iox2/v1/channel/**".to_string(), announce("*")] {
        let heard = heard.clone();
        let subscriber = observer
            .declare_subscriber(key)
            .callback(move |sample| {
                heard
                    .lock()
                    .expect("heard")
                    .push(sample.key_expr().to_string())
            })
            .wait()
            .expect("subscriber");
        subscribers.push(subscriber);
    }
    let rogue = rogue_session(&hosts);
    let run_key = uavmeta_tunnel::session::run_key(hosts.run_a.id());
    wait_until("the tunnel to answer B", within(60), || {
        handshake_answers(&rogue, &run_key) > 0
    });
    assert_eq!(
        handshake_answers(&session_as(&hosts, "hostd"), &run_key),
        0,
        "a host not in tunnel.hosts was answered"
    );
    let heard_own = || heard.lock().expect("heard").contains(&own);
    wait_until("C to hear B on B's own channel", within(60), || {
        rogue.put(&own, "frame").wait().expect("put");
        std::thread::sleep(Duration::from_millis(50));
        heard_own()
    });
    for key in forbidden.iter().cloned().chain([announce("hostc")]) {
        // Refused on arrival at A's tunnel; a wildcard key may be refused by the API itself.
        let _ = rogue.put(key, "forged").wait();
    }
    let _ = rogue.put("iox2/v1/channel/**", "forged").wait();
    heard.lock().expect("heard").clear();
    // The same session's later puts arrive after the earlier ones: once these are heard, the
    // forged ones had their chance.
    rogue.put(announce("hostb"), "{}").wait().expect("put");
    wait_until("C to hear B's later puts", within(60), || {
        rogue.put(&own, "frame").wait().expect("put");
        std::thread::sleep(Duration::from_millis(50));
        heard_own()
    });
    let heard_keys = heard.lock().expect("heard").clone();
    assert!(
        heard_keys.contains(&announce("hostb")),
        "B's own announcement key: {heard_keys:?}"
    );
    for key in forbidden.iter().chain([&announce("hostc")]) {
        assert!(!heard_keys.contains(key), "B put on {key}: {heard_keys:?}");
    }
    assert!(
        heard_keys
            .iter()
            .all(|k| *k == own || *k == announce("hostb")),
        "{heard_keys:?}"
    );
    drop((subscribers, rogue, observer));

    // `join` refuses a --host other than its certificate's name before it connects.
    let mut args = strings(&["tunnel", "join", "--connect", &hosts.endpoint, "--run-id"]);
    args.extend(strings(&[
        hosts.run_a.id(),
        "--dir",
        "unused",
        "--host",
        "hostc",
    ]));
    args.extend(hosts.b_credentials());
    let posing = Proc::spawn("posing", &args).wait(within(60));
    assert!(
        !posing.status.success() && posing.stderr.contains("names hostb"),
        "{}",
        posing.stderr
    );

    let join = hosts.join(hosts.run_a.id());
    let refused = hosts.actor_b("lambda-100", &[]).wait(within(60));
    assert!(
        !refused.status.success() && refused.stderr.contains("may not serve it"),
        "{}",
        refused.stderr
    );
    hosts
        .actor_b("lambda-0", &["--transitions", "2000"])
        .succeeds(within(120));
    wait_until("B's share in A's store", within(60), || {
        stored(&hosts.run_a) >= 1500.0
    });
    let run = hosts.run_a.root().display().to_string();
    let local = strings(&[
        "actor", "--run", &run, "--task", "lambda-0", "--seed", "100", "--policy", "random",
    ]);
    Proc::spawn("actor-a", &local).succeeds(within(120));
    store.signal(libc::SIGTERM);
    store.succeeds(within(60));
    drop(join);
    let reader = dataset_a(&hosts, "lambda-0");
    let made: Vec<(&str, u64)> = reader.provenance().into_iter().collect();
    assert_eq!(
        made,
        [("", 1500), ("hostb", 1500)],
        "who made lambda-0's dataset"
    );
    let ids: std::collections::BTreeSet<u32> =
        reader.transitions().iter().map(|t| t.actor).collect();
    assert_eq!(ids.len(), 1, "A's actor and B's share one id: {ids:?}");
    let file = hosts.run_a.root().join("datasets").join("lambda-0.uavds");
    let inspect = Proc::spawn(
        "inspect",
        &strings(&["dataset", "inspect", &file.display().to_string()]),
    )
    .succeeds(within(60));
    assert!(
        inspect
            .stdout
            .contains("made by      learner host 1500, hostb 1500"),
        "{}",
        inspect.stdout
    );
}
