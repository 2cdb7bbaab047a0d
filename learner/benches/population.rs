//! Populations (issue #33): learner-steps per second of N stacked Q-networks trained in lockstep,
//! at N = 1, 8, 32 and 80, beside the floor the step's matrix products set.
//!
//! Network: K = 10 (12 inputs, 50 actions), hidden [256, 256]; batch 64 per member; one libtorch
//! thread. Two steps, each on a fixed minibatch per member (sampling is the caller's and is not
//! timed):
//! - `dqn`: the online agents' step: Double DQN (eq. 7 with the online network's argmax), Huber,
//!   per-member gradient clipping at 10, fused Adam (`learner::optim`);
//! - `cql`: eq. 8 with eq. 7's plain max, fused Adam.
//!
//! The floor is the same step's matrix products alone, the same shapes timed in isolation:
//! forward passes (three for `dqn`: online on s, target and online on s'; two for `cql`) and the
//! backward pass's weight and input gradients (five products: the first layer's input needs no
//! gradient). `of floor` is floor time / step time: how much of the step is arithmetic.
//!
//! `peak RSS` is the process's high-water mark (VmHWM) after the row's step ran; the sizes run in
//! ascending order, so each `dqn` row's is its own peak, and `per member` is its growth over the
//! process's mark before any population was built, divided by N (the `cql` rows, run after
//! N = 80, show no memory of their own).
//!
//! Run: `cargo bench --bench population` (`-- --textbook-adam` for tch's `nn::Adam` in place of
//! the fused kernel) (prints a Markdown table; docs/BENCHMARKS.md,
//! "Populations"; `benches/pytorch_reference.py --population` is the PyTorch side).

use std::time::Instant;

use tch::nn::{self, OptimizerConfig};
use tch::{Device, Kind, Tensor};
use uavmeta_learner::batch::Batch;
use uavmeta_learner::cql::conservative_rows;
use uavmeta_learner::dqn::{Bootstrap, TdConfig};
use uavmeta_learner::optim::FusedAdam;
use uavmeta_learner::population::QPopulation;
use uavmeta_learner::qnet::QNetworkConfig;

const OBS: i64 = 12;
const ACTIONS: i64 = 50;
const HIDDEN: i64 = 256;
const BATCH: i64 = 64;
const SIZES: [usize; 4] = [1, 8, 32, 80];

/// Median over `rounds` rounds of the mean seconds per call of `f`, after a warm-up.
fn median_seconds(mut f: impl FnMut(), per_round: usize, rounds: usize) -> f64 {
    for _ in 0..per_round.min(10) {
        f();
    }
    let mut times: Vec<f64> = (0..rounds)
        .map(|_| {
            let start = Instant::now();
            for _ in 0..per_round {
                f();
            }
            start.elapsed().as_secs_f64() / per_round as f64
        })
        .collect();
    times.sort_by(f64::total_cmp);
    times[rounds / 2]
}

/// A fixed minibatch per member: [N, B, ..].
fn minibatch(n: usize) -> Batch {
    tch::manual_seed(0);
    let cpu = (Kind::Float, Device::Cpu);
    let n = n as i64;
    Batch {
        obs: Tensor::rand([n, BATCH, OBS], cpu),
        actions: Tensor::randint(ACTIONS, [n, BATCH], (Kind::Int64, Device::Cpu)),
        rewards: -Tensor::rand([n, BATCH], cpu),
        next_obs: Tensor::rand([n, BATCH, OBS], cpu),
    }
}

#[derive(Clone, Copy, PartialEq)]
enum Step {
    Dqn,
    Cql,
}

impl Step {
    fn name(self) -> &'static str {
        match self {
            Step::Dqn => "dqn (double, Huber, clip)",
            Step::Cql => "cql (eq. 8)",
        }
    }

    fn forward_passes(self) -> usize {
        match self {
            Step::Dqn => 3,
            Step::Cql => 2,
        }
    }
}

/// Seconds per lockstep step of `n` members, with the fused Adam of `learner::optim` or, for
/// `textbook`, tch's `nn::Adam` (libtorch's C++ `torch::optim::Adam`, the optimiser before).
fn step_seconds(step: Step, n: usize, per_round: usize, textbook: bool) -> f64 {
    let shape = QNetworkConfig::new(OBS as usize, ACTIONS as usize, &[256, 256]);
    let seeds: Vec<u64> = (0..n as u64).collect();
    let q = QPopulation::init(&shape, &seeds, Device::Cpu);
    let target = q.duplicate();
    let mut fused = FusedAdam::new(q.parameters(), 1e-4);
    let mut nn_adam = nn::Adam::default().build(&q.vs, 1e-4).expect("Adam builds");
    let mb = minibatch(n);
    let td = TdConfig {
        gamma: 0.99,
        bootstrap: match step {
            Step::Dqn => Bootstrap::Double,
            Step::Cql => Bootstrap::Max,
        },
        huber: step == Step::Dqn,
    };
    median_seconds(
        || {
            let q_all = q.forward(&mb.obs); // [N, B, A]
            let errors = td.td_errors(&q_all, &mb, |s| target.forward(s), |s| q.forward(s));
            let per_member = |t: Tensor| t.mean_dim([-1i64].as_slice(), false, None);
            let loss = match step {
                Step::Dqn => per_member(errors),
                // eq. 8: 0.5 * eq. 7 + alpha * conservative term, each member's own means.
                Step::Cql => per_member(errors) * 0.5 + per_member(conservative_rows(&q_all, &mb)),
            }
            .sum(None);
            fused.zero_grad();
            loss.backward();
            if step == Step::Dqn {
                q.clip_grad_norm(10.0);
            }
            match textbook {
                true => nn_adam.step(),
                false => fused.step(),
            }
        },
        per_round,
        5,
    )
}

/// Seconds of the step's matrix products alone, for `n` members.
fn floor_seconds(step: Step, n: usize, per_round: usize) -> f64 {
    let n = n as i64;
    let f = (Kind::Float, Device::Cpu);
    let widths = [OBS, HIDDEN, HIDDEN, ACTIONS];
    // Layer l: x [N, B, in] and W^T [N, in, out]; its output gradient g [N, B, out] and W [N, out, in].
    let layers: Vec<(Tensor, Tensor, Tensor, Tensor)> = widths
        .windows(2)
        .map(|w| {
            (
                Tensor::rand([n, BATCH, w[0]], f),
                Tensor::rand([n, w[0], w[1]], f),
                Tensor::rand([n, BATCH, w[1]], f),
                Tensor::rand([n, w[1], w[0]], f),
            )
        })
        .collect();
    let forwards = step.forward_passes();
    median_seconds(
        || {
            for _ in 0..forwards {
                for (x, wt, _, _) in &layers {
                    let _ = x.bmm(wt);
                }
            }
            for (i, (x, _, g, w)) in layers.iter().enumerate() {
                let _ = g.transpose(1, 2).bmm(x); // dL/dW [N, out, in]
                if i > 0 {
                    let _ = g.bmm(w); // dL/dx [N, B, in]
                }
            }
        },
        per_round,
        5,
    )
}

/// Multiply-adds times two of the step's products, per member.
fn flops(step: Step) -> f64 {
    let per_layer: Vec<f64> = [(OBS, HIDDEN), (HIDDEN, HIDDEN), (HIDDEN, ACTIONS)]
        .iter()
        .map(|&(i, o)| 2.0 * (BATCH * i * o) as f64)
        .collect();
    let forward: f64 = per_layer.iter().sum();
    let backward = 2.0 * forward - per_layer[0];
    step.forward_passes() as f64 * forward + backward
}

/// The process's peak resident size so far, in MiB (VmHWM).
fn peak_rss_mib() -> f64 {
    let status = std::fs::read_to_string("/proc/self/status").unwrap_or_default();
    status
        .lines()
        .find_map(|l| l.strip_prefix("VmHWM:"))
        .and_then(|v| v.trim().trim_end_matches("kB").trim().parse::<f64>().ok())
        .map_or(f64::NAN, |kib| kib / 1024.0)
}

fn main() {
    // The numerics the binary runs with (learner::numerics).
    uavmeta_learner::numerics::pin().expect("UAVMETA_NUMERICS is a known mode");
    // One intra-op thread: the machine's two cores are shared (docs/BENCHMARKS.md, "Threads").
    tch::set_num_threads(1);
    let textbook = std::env::args().any(|a| a == "--textbook-adam");
    let base_rss = peak_rss_mib();
    println!("| step | N | step (ms) | learner-steps/s | x N=1 | floor (ms) | of floor | GFLOP/s | peak RSS (MiB) | per member (MiB) |");
    println!("| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |");
    for step in [Step::Dqn, Step::Cql] {
        let mut single = None;
        for n in SIZES {
            let per_round = (400 / n).max(5);
            let t = step_seconds(step, n, per_round, textbook);
            let rss = match step {
                Step::Dqn => peak_rss_mib(),
                Step::Cql => f64::NAN,
            };
            let floor = floor_seconds(step, n, per_round);
            let rate = n as f64 / t;
            let base = *single.get_or_insert(rate);
            println!(
                "| {} | {n} | {:.2} | {rate:.0} | {:.2} | {:.2} | {:.0}% | {:.1} | {rss:.0} | {:.2} |",
                step.name(),
                t * 1e3,
                rate / base,
                floor * 1e3,
                100.0 * floor / t,
                flops(step) * n as f64 / t / 1e9,
                (rss - base_rss) / n as f64,
            );
        }
    }
}
