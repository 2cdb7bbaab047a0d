//! Seconds per outer step and peak memory of MAML (Algorithm 4) on the paper's network.
//!
//! `cargo bench -p uavmeta-meta --bench maml` runs every setting in a child process of its own, so
//! each peak resident size (VmHWM from /proc/self/status) belongs to that setting alone, and prints
//! a Markdown table. Setting: K = 10 devices (12 inputs, 50 actions), hidden [256, 256], 8 tasks
//! per outer step, 64 support shots and 64 query shots per task, CQL inner loss.

use std::process::Command;
use std::time::{Duration, Instant};

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use tch::Tensor;
use uavmeta_learner::qnet::QNetworkConfig;
use uavmeta_learner::transitions::Transitions;
use uavmeta_meta::maml::{Maml, MamlConfig, MetaTask};
use uavmeta_proto::config::Config;

const TASKS: usize = 8;
const ROWS: usize = 250;
const WARMUP_EPOCHS: usize = 3;
const MIN_EPOCHS: usize = 10;
const MIN_TIME: Duration = Duration::from_secs(3);

fn random_batch(config: &Config, rng: &mut ChaCha8Rng) -> Transitions {
    let d = config.world.layout().observation_len();
    let a = config.world.layout().action_count();
    let mut uniform =
        |n: usize| -> Vec<f32> { (0..n).map(|_| rng.random_range(0.0..1.0)).collect() };
    let obs = uniform(ROWS * d);
    let next_obs = uniform(ROWS * d);
    let rewards: Vec<f32> = uniform(ROWS).iter().map(|u| -u).collect();
    let actions: Vec<i64> = uniform(ROWS)
        .iter()
        .map(|u| (u * a as f32) as i64)
        .collect();
    Transitions {
        obs: Tensor::from_slice(&obs).view([ROWS as i64, d as i64]),
        actions: Tensor::from_slice(&actions),
        rewards: Tensor::from_slice(&rewards),
        next_obs: Tensor::from_slice(&next_obs).view([ROWS as i64, d as i64]),
    }
}

/// Peak resident set size of this process in KiB.
fn vm_hwm_kib() -> u64 {
    let status = std::fs::read_to_string("/proc/self/status").expect("Linux /proc/self/status");
    status
        .lines()
        .find_map(|l| l.strip_prefix("VmHWM:"))
        .and_then(|v| v.trim().trim_end_matches("kB").trim().parse().ok())
        .expect("a VmHWM line in /proc/self/status")
}

/// One setting, in this process (`threads` = 0 keeps libtorch's default): prints
/// `seconds_per_meta_epoch peak_kib_before peak_kib_after`.
fn child(inner_steps: usize, first_order: bool, threads: i32) {
    if threads > 0 {
        tch::set_num_threads(threads);
    }
    let mut config = Config::default();
    config.meta.inner_steps = inner_steps;
    config.meta.first_order = first_order;
    // One outer step per timed call (Algorithm 4's meta-epoch); docs/MODEL.md's meta-epoch, a pass
    // over these 250 support shots per task, is four of them.
    config.meta.outer_steps_per_meta_epoch = 1;
    let mut rng = ChaCha8Rng::seed_from_u64(0);
    let tasks: Vec<MetaTask> = (0..TASKS)
        .map(|i| MetaTask {
            name: format!("task-{i}"),
            support: random_batch(&config, &mut rng),
            query: random_batch(&config, &mut rng),
        })
        .collect();
    let net = QNetworkConfig::for_world(&config.world, &config.learner.hidden).init(0);
    let mut maml = Maml::new(net, MamlConfig::from_config(&config), 0).expect("Adam builds");
    let before = vm_hwm_kib();
    for _ in 0..WARMUP_EPOCHS {
        maml.meta_epoch(&tasks).expect("tasks");
    }
    let started = Instant::now();
    let mut times = Vec::new();
    while times.len() < MIN_EPOCHS || started.elapsed() < MIN_TIME {
        let epoch = Instant::now();
        maml.meta_epoch(&tasks).expect("tasks");
        times.push(epoch.elapsed().as_secs_f64());
    }
    // The median, robust to the other processes of a shared machine.
    times.sort_by(f64::total_cmp);
    println!("{} {before} {}", times[times.len() / 2], vm_hwm_kib());
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    if let Some(i) = args.iter().position(|a| a == "--child") {
        let inner_steps = args[i + 1].parse().expect("inner steps");
        let first_order = args[i + 2] == "first";
        let threads = args[i + 3].parse().expect("threads");
        child(inner_steps, first_order, threads);
        return;
    }
    let exe = std::env::current_exe().expect("the bench executable");
    println!("| inner steps | order | libtorch threads | s / outer step (median) | peak RSS (MiB) | peak RSS growth over the set-up (MiB) |");
    println!("| --- | --- | --- | --- | --- | --- |");
    for inner_steps in [1, 5] {
        for order in ["second", "first"] {
            for threads in [0, 1] {
                let out = Command::new(&exe)
                    .args([
                        "--child",
                        &inner_steps.to_string(),
                        order,
                        &threads.to_string(),
                    ])
                    .output()
                    .expect("run the child bench");
                assert!(
                    out.status.success(),
                    "child failed: {}",
                    String::from_utf8_lossy(&out.stderr)
                );
                let text = String::from_utf8_lossy(&out.stdout);
                let fields: Vec<f64> = text
                    .split_whitespace()
                    .map(|f| f.parse().expect("child prints numbers"))
                    .collect();
                let (seconds, before, after) = (fields[0], fields[1], fields[2]);
                let threads = if threads == 0 {
                    "default".to_string()
                } else {
                    threads.to_string()
                };
                println!(
                    "| {inner_steps} | {order} | {threads} | {seconds:.4} | {:.1} | {:.1} |",
                    after / 1024.0,
                    (after - before) / 1024.0
                );
            }
        }
    }
}
