//! Transport benchmark: transitions per second from 1, 2 and 4 real `uavmeta actor` processes
//! over iceoryx2 at batch sizes 1, 64 and 1024, with publish-to-receive latency percentiles, beside
//! the speed of the same rollout without any transport; and what iceoryx2 alone costs per batch,
//! and what the transport costs an actor under each behaviour policy.
//!
//! The transport's cost to an actor is its CPU time per transition over the environment's CPU time
//! per step, minus one. The environment steps the same policy in the same world (same K, episodes
//! seeded as the actor seeds them) and records nothing. An actor's CPU time is its main thread's
//! run time (`/proc/PID/schedstat`) from the first batch received to the last, so it leaves out
//! starting (loading libtorch alone takes about 0.25 s of CPU) and includes rolling out, writing
//! each step into its shared-memory slot, sending, and the actor's metrics. CPU time, not wall
//! time, because the machine is shared: another process taking turns on a core slows the wall
//! clock but not the CPU time of the work measured. The in-process CPU rate of the actor's own
//! rollout writing into a local batch splits the cost into writing and sending.
//!
//! The receiving side is this process: it subscribes to the task's transition service exactly as
//! the store does (`proto::transport`), but only counts, so the figures are the transport's, not
//! the dataset writer's; it acknowledges every batch as the store does (`StoreAck`), so actors keep
//! what they keep in a run. Run: `cargo bench --bench transport` (prints Markdown tables);
//! arguments pick sections (`floor`, `policies`, `actors`, `tunnel`) and `ACTORSxBATCH`
//! (e.g. `-- 1x64`) only those actor cases.
//!
//! `tunnel` puts the actor on a second host (issue #16): the bench's run is host A, served by a
//! real `uavmeta tunnel serve`; a real `uavmeta tunnel join` makes host B's directory for it in an
//! iceoryx2 domain of its own (`run.domain`), and the actor publishes there, so its batches and
//! the receiver's acknowledgements cross a loopback Zenoh link, as in tests/remote.rs. Same-host
//! and tunnel cases take turns, several rounds; the receiver waits as the store does when nothing
//! arrived (`store::IDLE_WAIT`), since a busy-polling one would take a core from the tunnel.

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::time::{Duration, Instant};

use iceoryx2::node::Node;
use iceoryx2::port::publisher::Publisher;
use iceoryx2::prelude::ipc;

use uavmeta_proto::config::{Config, RunConfig};
use uavmeta_proto::payload::{ServiceNames, StoreAck, TransitionSlot, SCHEMA_VERSION};
use uavmeta_runtime::actor::{ActorOptions, Rollout};
use uavmeta_runtime::domain;
use uavmeta_runtime::run_dir::RunDir;
use uavmeta_runtime::store;
use uavmeta_runtime::transport::{self, TransitionPublisher};
use uavmeta_world::heuristics::PolicySpec;
use uavmeta_world::rollout::{episode_seed, run_episode, Policy};
use uavmeta_world::world::World;

const BIN: &str = env!("CARGO_BIN_EXE_uavmeta");

#[path = "transport/validation.rs"]
mod validation;

/// Transitions each actor publishes, per batch size: enough for about a second of sending.
fn per_actor(batch: usize) -> u64 {
    if batch == 1 {
        200_000
    } else {
        3_000_000
    }
}

/// Steps of each in-process measurement, and how many times it is repeated (the best counts:
/// the machine is shared, and interference only ever slows a run down). The measurements being
/// compared take turns, so that a spell of interference hits them alike.
const RAW_STEPS: usize = 2_000_000;
const RAW_REPEATS: usize = 8;

/// Runs of each actor case; the one whose actors spent the least CPU per transition counts, for
/// the same reason.
const CASE_REPEATS: usize = 3;

/// Rounds of the tunnel section, each running every batch size same-host and across the tunnel.
const TUNNEL_ROUNDS: usize = 5;

/// CPU time of this thread.
fn cpu_time() -> Duration {
    // SAFETY: clock_gettime writes the struct it is given.
    let t = unsafe {
        let mut t = std::mem::zeroed::<libc::timespec>();
        libc::clock_gettime(libc::CLOCK_THREAD_CPUTIME_ID, &mut t);
        t
    };
    Duration::new(t.tv_sec as u64, t.tv_nsec as u32)
}

/// CPU time (user and system) of all of process `pid`'s threads so far, in clock ticks' precision.
fn process_cpu(pid: u32) -> Duration {
    let path = format!("/proc/{pid}/stat");
    let text = std::fs::read_to_string(&path).unwrap_or_else(|e| panic!("{path}: {e}"));
    // Fields 14 and 15 (utime, stime), counted after the parenthesised command name.
    let fields: Vec<&str> = text
        .rsplit_once(')')
        .map_or(vec![], |(_, rest)| rest.split_whitespace().collect());
    let ticks: u64 = fields
        .get(11..13)
        .map(|f| f.iter().filter_map(|t| t.parse::<u64>().ok()).sum())
        .unwrap_or_else(|| panic!("{path}: `{text}` has no utime and stime"));
    // SAFETY: sysconf only reads a constant.
    let per_second = unsafe { libc::sysconf(libc::_SC_CLK_TCK) } as u64;
    Duration::from_nanos(ticks * 1_000_000_000 / per_second)
}

/// Time process `pid`'s main thread has run on a CPU so far.
fn run_time(pid: u32) -> Duration {
    let path = format!("/proc/{pid}/schedstat");
    let text = std::fs::read_to_string(&path).unwrap_or_else(|e| panic!("{path}: {e}"));
    let ns = text
        .split_whitespace()
        .next()
        .and_then(|n| n.parse().ok())
        .unwrap_or_else(|| panic!("{path}: `{text}` does not start with nanoseconds"));
    Duration::from_nanos(ns)
}

/// Steps per CPU-second of each of `runs` (each returns the steps it took), best of
/// `RAW_REPEATS` rounds in which every run takes its turn.
fn best_rates(runs: &mut [Box<dyn FnMut() -> usize + '_>]) -> Vec<f64> {
    let mut best = vec![0.0f64; runs.len()];
    for _ in 0..RAW_REPEATS {
        for (run, best) in runs.iter_mut().zip(&mut best) {
            let start = cpu_time();
            let steps = run();
            *best = best.max(steps as f64 / (cpu_time() - start).as_secs_f64());
        }
    }
    best
}

/// The behaviour policy `spec` as an actor with `--seed 0` builds it.
fn behaviour(config: &Config, spec: &PolicySpec) -> Box<dyn Policy> {
    spec.build(config, 0, None).expect("a rollout policy")
}

/// The environment alone: policy `spec` (an actor's `--seed 0`) in one task's world, episode i in
/// the world of `episode_seed(0, i)` as an actor runs it, recording nothing.
fn env_steps<'c>(config: &'c Config, spec: &PolicySpec) -> impl FnMut() -> usize + 'c {
    let task = &config.tasks[0];
    let mut world = World::new(&config.world, task, 0);
    let mut policy = behaviour(config, spec);
    let horizon = config.world.horizon as usize;
    let mut episode = 0;
    move || {
        for _ in 0..RAW_STEPS / horizon {
            world.reseed(episode_seed(0, episode));
            std::hint::black_box(run_episode(&mut world, policy.as_mut()));
            episode += 1;
        }
        RAW_STEPS / horizon * horizon
    }
}

/// An actor's own rollout of policy `spec` writing every step into a batch of `batch` slots in
/// local memory, sending nothing.
fn rollout_steps<'c>(
    config: &'c Config,
    spec: &PolicySpec,
    batch: usize,
) -> impl FnMut() -> usize + 'c {
    let task = &config.tasks[0];
    let mut rollout = Rollout::new(config, task, behaviour(config, spec), 0);
    let mut slots = vec![TransitionSlot::default(); batch];
    move || {
        for _ in 0..RAW_STEPS / batch {
            for slot in slots.iter_mut() {
                rollout.write_step(slot);
            }
            std::hint::black_box(&mut slots);
            rollout.drain_finished().for_each(drop);
        }
        RAW_STEPS / batch * batch
    }
}

struct Figures {
    /// Transitions per wall-clock second at the receiver.
    rate: f64,
    /// CPU seconds per transition of the actors, each from its first batch received to its last.
    cpu_per_transition: f64,
    /// CPU seconds per transition of the watched processes (all their threads) over the same
    /// span: the tunnel's two ends.
    watched_cpu_per_transition: f64,
    latencies: Vec<f64>,
}

fn percentile(sorted: &[f64], p: f64) -> f64 {
    sorted[((sorted.len() - 1) as f64 * p).round() as usize]
}

/// A run of one task, "bench", that sends batches of `batch`, in a directory removed on drop.
struct BenchRun {
    dir: tempfile::TempDir,
    run: RunDir,
    config: Config,
}

/// A tunnel's endpoint and host A's iceoryx2 domain, set in the bench run's config.
struct Served<'a> {
    endpoint: &'a str,
    domain: &'a str,
}

impl BenchRun {
    fn new(batch: usize, served: Option<Served>) -> Self {
        let dir = tempfile::Builder::new()
            .prefix("uavmeta-bench-")
            .tempdir()
            .expect("temp dir");
        let run = RunDir::create(&dir.path().join("run")).expect("run dir");
        let mut text = format!(
            "[[tasks]]\nname = \"bench\"\nlambda = 300.0\nrole = \"meta-test\"\n[collect]\ntransitions = 1000000000\n[run]\ntransitions_per_message = {batch}\n"
        );
        if let Some(Served { endpoint, domain }) = served {
            text += &format!("domain = \"{domain}\"\n[tunnel]\nlisten = \"{endpoint}\"\n");
        }
        std::fs::write(run.config_file(), &text).expect("config");
        let config = Config::load(&run.config_file(), &[]).expect("valid bench config");
        Self { dir, run, config }
    }

    fn service(&self, node: &Node<ipc::Service>) -> transport::TransitionService {
        let names = ServiceNames::new(self.run.id());
        transport::transition_service(node, &names, "bench", &self.config.run).expect("service")
    }
}

/// What iceoryx2 itself costs an actor per batch of `batch` slots: the wall time of loaning the
/// batch and sending it, with nothing written into it, through the actor's own publisher to a
/// subscriber polling on the other core. Between sends the publisher spins for as long as the
/// environment takes to make the batch (`step` per transition), so the subscriber has taken the
/// previous batch, as it has in an actor. Best of `RAW_REPEATS` rounds.
fn send_floor(batch: usize, step: Duration) -> Duration {
    let bench = BenchRun::new(batch, None);
    let stop = AtomicBool::new(false);
    let subscribed = AtomicBool::new(false);
    std::thread::scope(|scope| {
        scope.spawn(|| {
            let node =
                domain::node("transport-bench-floor-store", &bench.config.run).expect("node");
            let service = bench.service(&node);
            let subscriber =
                transport::transition_subscriber(&service, &bench.config.run).expect("subscriber");
            subscribed.store(true, Ordering::Release);
            while !stop.load(Ordering::Relaxed) {
                if subscriber.receive().expect("receive").is_none() {
                    std::hint::spin_loop();
                }
            }
        });
        while !subscribed.load(Ordering::Acquire) {
            std::thread::yield_now();
        }
        let node = domain::node("transport-bench-floor-actor", &bench.config.run).expect("node");
        let service = bench.service(&node);
        let publisher =
            TransitionPublisher::new(&service, &bench.run, &bench.config, 0, 0).expect("publisher");
        let batches = (RAW_STEPS / batch).clamp(5_000, 200_000);
        let gap = step * batch as u32;
        let mut seq = 0;
        let mut round = || {
            let (mut spent, mut timer) = (Duration::ZERO, Duration::ZERO);
            for _ in 0..batches {
                let until = Instant::now() + gap;
                while Instant::now() < until {
                    std::hint::spin_loop();
                }
                let start = Instant::now();
                publisher
                    .loan(seq, batch)
                    .expect("loan")
                    .send()
                    .expect("send");
                spent += start.elapsed();
                // What taking the time itself adds, taken off below.
                let start = Instant::now();
                timer += start.elapsed();
                seq += batch as u64;
            }
            spent.saturating_sub(timer) / batches as u32
        };
        round(); // connects the subscriber and warms the pool
        let best = (0..RAW_REPEATS).map(|_| round()).min().expect("rounds");
        stop.store(true, Ordering::Relaxed);
        best
    })
}

/// The best of `CASE_REPEATS` runs of [`run_case`].
fn best_case(actors: usize, batch: usize, policy: &PolicySpec) -> Figures {
    (0..CASE_REPEATS)
        .map(|_| run_case(actors, batch, policy))
        .min_by(|a, b| a.cpu_per_transition.total_cmp(&b.cpu_per_transition))
        .expect("runs")
}

fn run_case(actors: usize, batch: usize, policy: &PolicySpec) -> Figures {
    let bench = BenchRun::new(batch, None);
    measure(&bench, bench.run.root(), actors, policy, Idle::Spin, &[])
}

/// How the receiver passes the time when nothing arrived.
#[derive(Clone, Copy)]
enum Idle {
    /// Busy-polling: the figures are the transport's alone.
    Spin,
    /// Sleeping as the store does, which leaves the core to other processes.
    AsTheStore,
}

/// Starts `actors` actors of policy `policy` in run directory `actor_dir` (the bench's, or host
/// B's of the same run), receives everything they publish on the bench's run as the store would,
/// acknowledging every batch, and measures it; `watched` are processes whose CPU is counted too.
fn measure(
    bench: &BenchRun,
    actor_dir: &Path,
    actors: usize,
    policy: &PolicySpec,
    idle: Idle,
    watched: &[u32],
) -> Figures {
    let (run, config) = (&bench.run, &bench.config);
    let batch = config.run.transitions_per_message;
    let node = domain::node("transport-bench", &config.run).expect("node");
    let service = bench.service(&node);
    let subscriber = transport::transition_subscriber(&service, &config.run).expect("subscriber");
    // Acknowledged like the store does, after every batch, so actors keep what they would.
    let names = ServiceNames::new(run.id());
    let acks = transport::ack_publisher(
        &transport::ack_service(&node, &names, "bench", &config.run).expect("ack service"),
    )
    .expect("ack publisher");

    let n = per_actor(batch);
    let children: Vec<Child> = (0..actors)
        .map(|i| {
            Command::new(BIN)
                .args([
                    "actor",
                    "--run",
                    &actor_dir.display().to_string(),
                    "--task",
                    "bench",
                    "--policy",
                    &policy.to_string(),
                ])
                .args(["--seed", &i.to_string(), "--transitions", &n.to_string()])
                .stdout(Stdio::null())
                .stderr(Stdio::null())
                .spawn()
                .expect("start an actor")
        })
        .collect();

    let total = n * actors as u64;
    let mut received = 0u64;
    let mut latencies = Vec::with_capacity((total / batch as u64) as usize + 1);
    // Per actor (by id): its run time at its first batch, and the transitions received since.
    let ids: Vec<u32> = (0..actors)
        .map(|i| {
            ActorOptions {
                task: "bench".into(),
                policy: policy.clone(),
                seed: i as u64,
                transitions: Some(n),
            }
            .actor_id()
        })
        .collect();
    let mut since_first: Vec<Option<(Duration, u64)>> = vec![None; actors];
    let mut acknowledged = vec![0u64; actors];
    let mut last_ack_refresh = Instant::now();
    let mut first: Option<Instant> = None;
    let mut watched_at_first = Duration::ZERO;
    let deadline = Instant::now() + Duration::from_secs(300);
    while received < total {
        assert!(
            Instant::now() < deadline,
            "the bench stalled at {received} of {total}"
        );
        match subscriber.receive().expect("receive") {
            Some(sample) => {
                let header = sample.user_header();
                latencies.push(header.age_seconds());
                received += sample.payload().len() as u64;
                let next_seq = header.first_seq + header.count as u64;
                acknowledge(&acks, header.actor, next_seq);
                if first.is_none() {
                    first = Some(Instant::now());
                    watched_at_first = watched.iter().map(|&pid| process_cpu(pid)).sum();
                }
                let i = ids
                    .iter()
                    .position(|&id| id == header.actor)
                    .expect("a batch of one of the bench's actors");
                acknowledged[i] = next_seq;
                match &mut since_first[i] {
                    Some((_, count)) => *count += sample.payload().len() as u64,
                    none => *none = Some((run_time(children[i].id()), 0)),
                }
            }
            // Repeated as the store repeats them: with several actors, one actor's
            // acknowledgements can overwrite another's in the service's buffer, and an actor
            // whose window is full then waits for one that never comes.
            None if last_ack_refresh.elapsed() >= store::ACK_REFRESH_EVERY => {
                for (&actor, &next_seq) in ids.iter().zip(&acknowledged) {
                    acknowledge(&acks, actor, next_seq);
                }
                last_ack_refresh = Instant::now();
            }
            None => match idle {
                Idle::Spin => std::hint::spin_loop(),
                Idle::AsTheStore => std::thread::sleep(store::IDLE_WAIT),
            },
        }
    }
    let elapsed = first.map_or(Duration::ZERO, |f| f.elapsed());
    let watched_cpu = watched
        .iter()
        .map(|&pid| process_cpu(pid))
        .sum::<Duration>()
        - watched_at_first;
    // The actors have sent their last batch but are still alive: their exit is not counted.
    let (mut cpu, mut measured) = (Duration::ZERO, 0u64);
    for (child, since) in children.iter().zip(&since_first) {
        let (start, count) = since.expect("every actor sent");
        cpu += run_time(child.id()) - start;
        measured += count;
    }
    // Every actor waits for the acknowledgement of its last batch before exiting; repeated here
    // as the store repeats them, since other actors' acknowledgements may have overwritten it.
    for &actor in &ids {
        acknowledge(&acks, actor, n);
    }
    for mut child in children {
        let _ = child.wait();
    }
    latencies.sort_by(f64::total_cmp);
    Figures {
        rate: total as f64 / elapsed.as_secs_f64(),
        cpu_per_transition: cpu.as_secs_f64() / measured.max(1) as f64,
        watched_cpu_per_transition: watched_cpu.as_secs_f64() / total as f64,
        latencies,
    }
}

/// Tells `actor` (of task 0, the bench's only task) that the store holds everything before
/// `next_seq`, as the store's acknowledgement does.
fn acknowledge(acks: &Publisher<ipc::Service, StoreAck, ()>, actor: u32, next_seq: u64) {
    let ack = StoreAck {
        schema_version: SCHEMA_VERSION,
        task: 0,
        actor,
        reserved: 0,
        next_seq,
    };
    transport::acknowledge(acks, ack).expect("acknowledge");
}

/// Host B of a tunnel case, on this machine: `uavmeta tunnel serve` serves the bench's run
/// (host A, the receiver's) on a loopback Zenoh endpoint, and `uavmeta tunnel join` makes B's
/// directory for it in an iceoryx2 domain of its own, which only the tunnel connects to A's.
struct SecondHost {
    serve: Child,
    join: Child,
    /// B's directory for the run, where its actors run.
    dir: PathBuf,
    domains: [String; 2],
}

/// Tunnel cases so far in this process: each has domains of its own.
static TUNNEL_CASES: AtomicUsize = AtomicUsize::new(0);

/// One random-policy actor publishing batches of `batch`, on the receiver's host or on a second
/// host behind the tunnel.
fn route_case(batch: usize, tunnel: bool) -> Figures {
    let (random, idle) = (PolicySpec::Random, Idle::AsTheStore);
    if !tunnel {
        let bench = BenchRun::new(batch, None);
        return measure(&bench, bench.run.root(), 1, &random, idle, &[]);
    }
    let case = TUNNEL_CASES.fetch_add(1, Ordering::Relaxed);
    let id = format!("{}x{case}", std::process::id());
    let domains = [format!("tbench{id}a"), format!("tbench{id}b")];
    // A free loopback port: bound and released; Zenoh binds it a moment later.
    let port = std::net::TcpListener::bind("127.0.0.1:0")
        .and_then(|l| l.local_addr())
        .expect("a free port")
        .port();
    let endpoint = format!("tcp/127.0.0.1:{port}");
    let served = Served {
        endpoint: &endpoint,
        domain: &domains[0],
    };
    let bench = BenchRun::new(batch, Some(served));
    let host = SecondHost::start(&bench, &endpoint, domains);
    let watched = [host.serve.id(), host.join.id()];
    measure(&bench, &host.dir, 1, &random, idle, &watched)
}

impl SecondHost {
    /// Serves `bench`'s run on `endpoint` and joins it; returns once the join bridges.
    fn start(bench: &BenchRun, endpoint: &str, domains: [String; 2]) -> Self {
        let dir = bench.dir.path().join("host-b");
        let spawn = |name: &str, args: &[&str]| {
            let log = std::fs::File::create(bench.dir.path().join(format!("{name}.log")))
                .expect("log file");
            Command::new(BIN)
                .args(args)
                .stdout(Stdio::null())
                .stderr(log)
                .spawn()
                .unwrap_or_else(|e| panic!("cannot start {name}: {e}"))
        };
        let run = bench.run.root().display().to_string();
        let serve = spawn("serve", &["tunnel", "serve", "--run", &run]);
        let b_dir = dir.display().to_string();
        let join = spawn(
            "join",
            &[
                "tunnel",
                "join",
                "--connect",
                endpoint,
                "--run-id",
                bench.run.id(),
                "--dir",
                &b_dir,
                "--domain",
                &domains[1],
                "--host",
                "bench",
            ],
        );
        let host = Self {
            serve,
            join,
            dir,
            domains,
        };
        let log = bench.dir.path().join("join.log");
        let deadline = Instant::now() + Duration::from_secs(60);
        while !std::fs::read_to_string(&log)
            .is_ok_and(|l| l.contains("bridging the run's services"))
        {
            assert!(
                Instant::now() < deadline,
                "the tunnel's join never bridged:\n{}",
                std::fs::read_to_string(&log).unwrap_or_default()
            );
            std::thread::sleep(Duration::from_millis(20));
        }
        host
    }
}

/// Both ends stop on SIGTERM; then what their domains left is removed.
impl Drop for SecondHost {
    fn drop(&mut self) {
        for child in [&mut self.join, &mut self.serve] {
            // SAFETY: a signal to a child this bench started and has not reaped.
            unsafe { libc::kill(child.id() as i32, libc::SIGTERM) };
            let _ = child.wait();
        }
        for domain in &self.domains {
            let run = RunConfig {
                domain: domain.clone(),
                ..RunConfig::default()
            };
            domain::remove_domain(&run).expect("remove the domain's files");
        }
    }
}

fn main() {
    // `cargo bench` passes its own flags (`--bench`); sections are named, actor cases `AxB`.
    let args: Vec<String> = std::env::args()
        .skip(1)
        .filter(|a| !a.starts_with('-'))
        .collect();
    const SECTIONS: [&str; 5] = ["floor", "policies", "actors", "tunnel", "validation"];
    let (actor_counts, batches) = ([1, 2, 4], [1, 64, 1024]);
    let all_cases: Vec<String> = actor_counts
        .iter()
        .flat_map(|a| batches.iter().map(move |b| format!("{a}x{b}")))
        .collect();
    if let Some(bad) = args
        .iter()
        .find(|a| !SECTIONS.contains(&a.as_str()) && !all_cases.contains(a))
    {
        eprintln!(
            "transport bench: unknown argument `{bad}`; expected a section ({}) or an actor case \
             ACTORSxBATCH ({})",
            SECTIONS.join(", "),
            all_cases.join(", ")
        );
        std::process::exit(2);
    }
    let cases: Vec<&String> = args.iter().filter(|a| all_cases.contains(a)).collect();
    let section = |name: &str| {
        args.is_empty() || args.iter().any(|a| a == name) || (name == "actors" && !cases.is_empty())
    };
    let config = Config::default();
    let mut runs: Vec<Box<dyn FnMut() -> usize>> =
        vec![Box::new(env_steps(&config, &PolicySpec::Random))];
    for batch in batches {
        runs.push(Box::new(rollout_steps(&config, &PolicySpec::Random, batch)));
    }
    let rates = best_rates(&mut runs);
    drop(runs);
    let env = rates[0];
    println!("## Transport\n");
    println!(
        "Environment alone, random policy, K = {}: {:.1} M steps per CPU-second ({:.1} ns per step).\n",
        config.world.devices,
        env / 1e6,
        1e9 / env
    );
    println!("| batch | rollout writing slots, in process (per CPU-second) | its cost over the environment |");
    println!("| ---: | ---: | ---: |");
    for (batch, rate) in batches.into_iter().zip(&rates[1..]) {
        println!(
            "| {batch} | {:.1} M/s | {:+.1}% |",
            rate / 1e6,
            100.0 * (env / rate - 1.0)
        );
    }
    println!();

    if section("validation") {
        validation::run();
    }
    if section("floor") {
        let step = Duration::from_secs_f64(1.0 / env);
        println!("| batch | iceoryx2 loan + send, nothing written | per transition | over the environment step |");
        println!("| ---: | ---: | ---: | ---: |");
        for batch in batches {
            let per_batch = send_floor(batch, step);
            let per_transition = per_batch.as_secs_f64() / batch as f64;
            println!(
                "| {batch} | {:.0} ns | {:.2} ns | {:+.1}% |",
                per_batch.as_secs_f64() * 1e9,
                per_transition * 1e9,
                100.0 * per_transition * env
            );
        }
        println!();
    }

    if section("policies") {
        println!("| policy (1 actor, batch 64) | environment per step | rollout writing slots, in process | actor CPU per transition | transport cost |");
        println!("| --- | ---: | ---: | ---: | ---: |");
        for spec in [PolicySpec::Random, PolicySpec::Stalest, PolicySpec::Greedy] {
            let rates = best_rates(&mut [
                Box::new(env_steps(&config, &spec)),
                Box::new(rollout_steps(&config, &spec, 64)),
            ]);
            let per_transition = best_case(1, 64, &spec).cpu_per_transition;
            println!(
                "| {spec} | {:.1} ns | {:.1} ns | {:.1} ns | {:+.0}% |",
                1e9 / rates[0],
                1e9 / rates[1],
                per_transition * 1e9,
                100.0 * (per_transition * rates[0] - 1.0)
            );
        }
        println!();
    }

    if section("actors") {
        println!(
            "| actors | batch | transitions/s | actor CPU per transition | transport cost per actor | latency p50 | p90 | p99 | max |"
        );
        println!("| ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |");
        for actors in actor_counts {
            for batch in batches {
                if !cases.is_empty() && !cases.iter().any(|c| **c == format!("{actors}x{batch}")) {
                    continue;
                }
                let f = best_case(actors, batch, &PolicySpec::Random);
                let l = &f.latencies;
                let per_transition = f.cpu_per_transition;
                println!(
                    "| {actors} | {batch} | {:.2} M | {:.1} ns | {:+.0}% | {:.1} µs | {:.1} µs | {:.1} µs | {:.1} µs |",
                    f.rate / 1e6,
                    per_transition * 1e9,
                    100.0 * (per_transition * env - 1.0),
                    percentile(l, 0.5) * 1e6,
                    percentile(l, 0.9) * 1e6,
                    percentile(l, 0.99) * 1e6,
                    l[l.len() - 1] * 1e6,
                );
            }
        }
    }

    if section("tunnel") {
        tunnel_section();
    }
}

/// One actor on the receiver's host against one across the tunnel, at batch 64 and 1024:
/// `TUNNEL_ROUNDS` rounds in which every case takes its turn, so a spell of interference hits them
/// alike; best and median rate, median of each run's latency percentiles.
fn tunnel_section() {
    let batches = [64, 1024];
    let routes = [false, true];
    let mut runs: Vec<Vec<Figures>> = (0..batches.len() * routes.len())
        .map(|_| Vec::new())
        .collect();
    for round in 0..TUNNEL_ROUNDS {
        for (b, &batch) in batches.iter().enumerate() {
            for (r, &tunnel) in routes.iter().enumerate() {
                let f = route_case(batch, tunnel);
                let l = &f.latencies;
                eprintln!(
                    "round {round}, batch {batch}, {}: {:.3} M/s, p50 {:.1} µs, p99 {:.1} µs, actor CPU {:.1} ns and tunnel CPU {:.1} ns per transition",
                    if tunnel { "tunnel" } else { "same host" },
                    f.rate / 1e6,
                    percentile(l, 0.5) * 1e6,
                    percentile(l, 0.99) * 1e6,
                    f.cpu_per_transition * 1e9,
                    f.watched_cpu_per_transition * 1e9
                );
                runs[b * routes.len() + r].push(f);
            }
        }
    }
    let median = |mut values: Vec<f64>| {
        values.sort_by(f64::total_cmp);
        values[values.len() / 2]
    };
    println!(
        "| batch | route | transitions/s, best | median | latency p50 | p99 | actor CPU per transition | tunnel's CPU per transition |"
    );
    println!("| ---: | --- | ---: | ---: | ---: | ---: | ---: | ---: |");
    for (b, batch) in batches.iter().enumerate() {
        for (r, &tunnel) in routes.iter().enumerate() {
            let figures = &runs[b * routes.len() + r];
            let median_of =
                |value: &dyn Fn(&Figures) -> f64| median(figures.iter().map(value).collect());
            let best = figures.iter().map(|f| f.rate).fold(0.0, f64::max);
            let tunnel_cpu = median_of(&|f| f.watched_cpu_per_transition);
            println!(
                "| {batch} | {} | {:.2} M | {:.2} M | {:.1} µs | {:.1} µs | {:.1} ns | {} |",
                if tunnel {
                    "tunnel (loopback Zenoh)"
                } else {
                    "same host (shared memory)"
                },
                best / 1e6,
                median_of(&|f| f.rate) / 1e6,
                median_of(&|f| percentile(&f.latencies, 0.5)) * 1e6,
                median_of(&|f| percentile(&f.latencies, 0.99)) * 1e6,
                median_of(&|f| f.cpu_per_transition) * 1e9,
                if tunnel {
                    format!("{:.0} ns", tunnel_cpu * 1e9)
                } else {
                    "–".into()
                }
            );
        }
    }
}
