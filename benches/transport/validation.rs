//! The `validation` section: what checking every transition against the world
//! (`uavmeta_world::validate`, issue #31) costs the store.
//!
//! A real `uavmeta store` receives 3 M transitions from one real random-policy actor at batch 64
//! and 1024; its CPU time (all threads, /proc) from ready to the last transition stored, per
//! transition, is what storing one costs it with validation. The checks alone are then timed in
//! this process on the same kind of transitions (a random policy's, in the bench task's world),
//! best of several rounds. The store's rate without validation is its CPU time per transition
//! minus the checks'. CPU time, not wall time: the actor, not the store, sets the wall-clock pace,
//! and the machine is shared.

use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use uavmeta_proto::config::Config;
use uavmeta_proto::metrics::store::DATASET_TRANSITIONS;
use uavmeta_proto::payload::TransitionSlot;
use uavmeta_runtime::metrics::{parse, scrape, sum};
use uavmeta_world::validate::{Claimed, Validator};
use uavmeta_world::world::World;

use super::{cpu_time, process_cpu, BenchRun, BIN, RAW_REPEATS};

const TRANSITIONS: u64 = 3_000_000;

/// Prints the section's table.
pub fn run() {
    println!("### Validation in the store\n");
    println!("| batch | store CPU per transition stored | of which the checks | checks' share | store rate per CPU-second, checks on | checks off |");
    println!("| ---: | ---: | ---: | ---: | ---: | ---: |");
    for batch in [64, 1024] {
        let bench = BenchRun::new(batch, None);
        let store = store_cpu_per_transition(&bench);
        let checks = checks_cpu_per_transition(&bench.config);
        println!(
            "| {batch} | {:.0} ns | {:.0} ns | {:.1}% | {:.2} M/s | {:.2} M/s |",
            store * 1e9,
            checks * 1e9,
            100.0 * checks / store,
            1e-6 / store,
            1e-6 / (store - checks)
        );
    }
    println!();
}

/// The store's CPU seconds per transition stored, from its port file to its last transition.
fn store_cpu_per_transition(bench: &BenchRun) -> f64 {
    let run = bench.run.root().display().to_string();
    let mut store = Command::new(BIN)
        .args(["store", "--run", &run])
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .expect("start the store");
    let port_file = bench.run.port_file("store");
    let port = wait_for(|| {
        std::fs::read_to_string(&port_file)
            .ok()?
            .trim()
            .parse()
            .ok()
    });
    let before = process_cpu(store.id());
    let status = Command::new(BIN)
        .args([
            "actor", "--run", &run, "--task", "bench", "--policy", "random", "--seed", "0",
        ])
        .args(["--transitions", &TRANSITIONS.to_string()])
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .status()
        .expect("run the actor");
    assert!(status.success(), "the bench actor failed");
    wait_for(|| {
        let samples = parse(&scrape("127.0.0.1", port).ok()?).ok()?;
        (sum(&samples, DATASET_TRANSITIONS, &[]) >= TRANSITIONS as f64).then_some(())
    });
    let cpu = process_cpu(store.id()) - before;
    // SAFETY: a signal to the store this bench started.
    unsafe { libc::kill(store.id() as libc::pid_t, libc::SIGTERM) };
    store.wait().expect("the store exits");
    cpu.as_secs_f64() / TRANSITIONS as f64
}

/// CPU seconds per transition of the checks alone, best of `RAW_REPEATS` rounds.
fn checks_cpu_per_transition(config: &Config) -> f64 {
    let task = &config.tasks[0];
    let slots = random_policy_slots(config, 1 << 16);
    let obs_len = config.world.layout().observation_len();
    let mut validator = Validator::new(&config.world, task);
    let mut best = f64::INFINITY;
    for _ in 0..RAW_REPEATS {
        let start = cpu_time();
        for _ in 0..TRANSITIONS as usize / slots.len() {
            for slot in &slots {
                std::hint::black_box(validator.check(Claimed::from_slot(slot, obs_len)))
                    .expect("a real transition passes");
            }
        }
        let per = (cpu_time() - start).as_secs_f64()
            / (TRANSITIONS as usize / slots.len() * slots.len()) as f64;
        best = best.min(per);
    }
    best
}

/// `count` steps of a uniformly random policy in the bench task's world, written into slots.
fn random_policy_slots(config: &Config, count: usize) -> Vec<TransitionSlot> {
    use rand::{Rng, SeedableRng};
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(0);
    let mut world = World::new(&config.world, &config.tasks[0], 0);
    let mut slots = vec![TransitionSlot::default(); count];
    for slot in &mut slots {
        if world.t() >= world.horizon() {
            world.reset();
        }
        slot.set_state(0, world.t(), world.observation());
        let action = rng.random_range(0..world.layout().action_count());
        let step = world.step(action);
        slot.set_outcome(
            action as u16,
            step.reward as f32,
            world.observation(),
            step.truncated,
        );
    }
    slots
}

/// Polls `ready` every 20 ms until it gives a value, for at most 10 minutes.
fn wait_for<T>(mut ready: impl FnMut() -> Option<T>) -> T {
    let start = Instant::now();
    loop {
        if let Some(value) = ready() {
            return value;
        }
        assert!(
            start.elapsed() < Duration::from_secs(600),
            "the bench store never got there"
        );
        std::thread::sleep(Duration::from_millis(20));
    }
}
