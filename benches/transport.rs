//! Transport benchmark: transitions per second from 1, 2 and 4 real `uavmeta actor` processes
//! over iceoryx2 at batch sizes 1, 64 and 1024, with publish-to-receive latency percentiles, beside
//! the raw speed of the same rollout without any transport.
//!
//! The receiving side is this process: it subscribes to the task's transition service exactly as
//! the store does (`proto::transport`), but only counts, so the figures are the transport's, not
//! the dataset writer's. Run: `cargo bench --bench transport` (prints a Markdown table).

use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use uavmeta_actors::heuristics::RandomPolicy;
use uavmeta_actors::rollout::Policy;
use uavmeta_actors::world::World;
use uavmeta_proto::config::Config;
use uavmeta_proto::transport::{self, RunDir, ServiceNames, TransitionSlot};

const BIN: &str = env!("CARGO_BIN_EXE_uavmeta");

/// Transitions each actor publishes, per batch size: enough for about a second of sending.
fn per_actor(batch: usize) -> u64 {
    if batch == 1 {
        200_000
    } else {
        3_000_000
    }
}

/// Steps per second of the random policy in one task's world, writing each step into a slot as an
/// actor does, but sending nothing.
fn raw_rollout_speed(config: &Config) -> f64 {
    let task = &config.tasks[0];
    let mut world = World::new(&config.world, task, 1);
    let mut policy = RandomPolicy::new(1);
    let mut slots = vec![TransitionSlot::new(0, 0, &[], 0, 0.0, &[], false); 64];
    let steps = 4_000_000;
    let start = Instant::now();
    world.reset();
    for i in 0..steps {
        let slot = &mut slots[i % 64];
        *slot = TransitionSlot::new(0, world.t(), world.observation(), 0, 0.0, &[], false);
        let action = policy.act(&world);
        let step = world.step(action);
        slot.action = action as u16;
        slot.reward = step.reward as f32;
        let next = world.observation();
        slot.next_obs[..next.len()].copy_from_slice(next);
        if step.truncated {
            world.reset();
        }
    }
    std::hint::black_box(&slots);
    steps as f64 / start.elapsed().as_secs_f64()
}

struct Figures {
    rate: f64,
    latencies: Vec<f64>,
}

fn percentile(sorted: &[f64], p: f64) -> f64 {
    sorted[((sorted.len() - 1) as f64 * p).round() as usize]
}

fn run_case(actors: usize, batch: usize) -> Figures {
    let dir = tempfile::Builder::new()
        .prefix("uavmeta-bench-")
        .tempdir()
        .expect("temp dir");
    let run = RunDir::create(&dir.path().join("run")).expect("run dir");
    let text = format!(
        "[[tasks]]\nname = \"bench\"\nlambda = 300.0\nrole = \"meta-test\"\n[collect]\ntransitions = 1000000000\n[run]\nbatch_size = {batch}\n"
    );
    std::fs::write(run.config_file(), &text).expect("config");
    let config = Config::load(&run.config_file(), &[]).expect("valid bench config");
    let node = transport::node("transport-bench").expect("node");
    let names = ServiceNames::new(&run);
    let service =
        transport::transition_service(&node, &names, "bench", &config.run).expect("service");
    let subscriber = transport::transition_subscriber(&service, &config.run).expect("subscriber");

    let n = per_actor(batch);
    let children: Vec<Child> = (0..actors)
        .map(|i| {
            Command::new(BIN)
                .args([
                    "actor",
                    "--run",
                    &run.root().display().to_string(),
                    "--task",
                    "bench",
                    "--policy",
                    "random",
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
    let mut first: Option<Instant> = None;
    let deadline = Instant::now() + Duration::from_secs(300);
    while received < total {
        assert!(
            Instant::now() < deadline,
            "the bench stalled at {received} of {total}"
        );
        match subscriber.receive().expect("receive") {
            Some(sample) => {
                first.get_or_insert_with(Instant::now);
                latencies.push(sample.user_header().age_seconds());
                received += sample.payload().len() as u64;
            }
            None => std::hint::spin_loop(),
        }
    }
    let elapsed = first.map_or(Duration::ZERO, |f| f.elapsed());
    for mut child in children {
        let _ = child.wait();
    }
    latencies.sort_by(f64::total_cmp);
    Figures {
        rate: total as f64 / elapsed.as_secs_f64(),
        latencies,
    }
}

fn main() {
    let config = Config::default();
    let raw = raw_rollout_speed(&config);
    println!("## Transport\n");
    println!("Command: `cargo bench --bench transport` (2-core machine shared with other work; each actor a real `uavmeta actor --policy random` process, the receiver a busy-polling subscriber in the bench process).\n");
    println!("Raw rollout in one process, random policy, K = 10, writing slots but sending nothing: {:.1} M transitions/s.\n", raw / 1e6);
    println!(
        "| actors | batch | transitions/s | per actor vs raw | latency p50 | p90 | p99 | max |"
    );
    println!("| ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |");
    for actors in [1, 2, 4] {
        for batch in [1, 64, 1024] {
            let f = run_case(actors, batch);
            let l = &f.latencies;
            println!(
                "| {actors} | {batch} | {:.2} M | {:.0}% | {:.1} µs | {:.1} µs | {:.1} µs | {:.1} µs |",
                f.rate / 1e6,
                100.0 * f.rate / actors as f64 / raw,
                percentile(l, 0.5) * 1e6,
                percentile(l, 0.9) * 1e6,
                percentile(l, 0.99) * 1e6,
                l[l.len() - 1] * 1e6,
            );
        }
    }
}
