//! Environment steps per second: one world, and a batch of 64 worlds of one task (clones sharing
//! the power tables, each reseeded) stepped round-robin as a vectorised actor would, at K = 10 and
//! K = 50. Actions come from a precomputed list so the figure is the world's cost alone.
//!
//! `evaluate_greedy`: one greedy Q-policy evaluation (default world and network, one libtorch
//! thread) over 10 and 40 episodes, episode by episode (`rollout::evaluate` with a `QPolicy`, one
//! forward pass per step and episode) against the lockstep `q_policy::Evaluator` (one forward pass
//! per step over all episodes).

use std::hint::black_box;

use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use uavmeta_actors::policy::q_policy::{Evaluator, QPolicy};
use uavmeta_learner::qnet::QNetworkConfig;
use uavmeta_learner::train::EvaluatePolicy;
use uavmeta_proto::config::{Config, RainZone, TaskConfig};
use uavmeta_world::rollout::evaluate;
use uavmeta_world::world::World;

const STEPS: usize = 1 << 16;
const BATCH: usize = 64;

fn worlds(devices: usize, count: usize) -> (Vec<World>, Vec<usize>) {
    let mut config = Config::default();
    config.world.devices = devices;
    let task = TaskConfig::one_off(
        300.0,
        Some(RainZone {
            x0: 3,
            y0: 3,
            x1: 5,
            y1: 5,
        }),
    );
    let first = World::new(&config.world, &task, 0);
    let worlds = (0..count as u64)
        .map(|i| {
            let mut w = first.clone();
            w.reseed(i);
            w.reset();
            w
        })
        .collect();
    let mut rng = ChaCha8Rng::seed_from_u64(0);
    let actions = (0..STEPS)
        .map(|_| rng.random_range(0..5 * devices))
        .collect();
    (worlds, actions)
}

/// Steps every world of `worlds` once per action, resetting a world at its horizon.
fn run(worlds: &mut [World], actions: &[usize]) -> f64 {
    let mut total = 0.0;
    for &a in actions {
        for w in worlds.iter_mut() {
            let step = w.step(a);
            total += step.reward;
            if step.truncated {
                w.reset();
            }
        }
    }
    total
}

fn bench(c: &mut Criterion) {
    let mut group = c.benchmark_group("env");
    for devices in [10, 50] {
        let (mut one, actions) = worlds(devices, 1);
        group.throughput(Throughput::Elements(STEPS as u64));
        group.bench_function(format!("one world, K = {devices}"), |b| {
            b.iter(|| black_box(run(&mut one, black_box(&actions))))
        });
        let (mut batch, actions) = worlds(devices, BATCH);
        let actions = &actions[..STEPS / BATCH];
        group.bench_function(format!("{BATCH} worlds round-robin, K = {devices}"), |b| {
            b.iter(|| black_box(run(&mut batch, black_box(actions))))
        });
    }
    group.finish();
}

fn bench_evaluate_greedy(c: &mut Criterion) {
    tch::set_num_threads(1);
    let config = Config::default();
    let task = TaskConfig::one_off(300.0, None);
    let q = QNetworkConfig::for_world(&config.world, &config.learner.hidden).init(0);
    let mut group = c.benchmark_group("evaluate_greedy");
    for episodes in [10, 40] {
        group.throughput(Throughput::Elements(
            (episodes * config.world.horizon as usize) as u64,
        ));
        group.bench_function(format!("episode by episode, {episodes} episodes"), |b| {
            b.iter(|| evaluate(&config.world, &task, &mut QPolicy::new(&q), episodes, 0))
        });
        let mut evaluator = Evaluator::new(&config.world, &task, episodes, 0);
        group.bench_function(format!("lockstep, {episodes} episodes"), |b| {
            b.iter(|| evaluator.evaluate(&q))
        });
    }
    group.finish();
}

criterion_group! {
    name = benches;
    config = Criterion::default()
        .warm_up_time(std::time::Duration::from_millis(500))
        .measurement_time(std::time::Duration::from_secs(2));
    targets = bench, bench_evaluate_greedy
}
criterion_main!(benches);
