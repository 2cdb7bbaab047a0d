//! CQL gradient steps per second (hidden [256, 256], K = 10: 12 inputs, 50 actions) at batch 64
//! and 256, and how much of a step is spent outside libtorch.
//!
//! - `cql_step/train/B`: the real path, `uavmeta_learner::train::train` for one epoch of many
//!   steps (minibatch draw, eq. 8, Adam, target sync, the per-step logged figures), divided by
//!   the steps. Its evaluation hook returns at once, so only gradient steps are timed.
//! - `cql_step/bare/B`: the same libtorch calls with nothing else: a fixed minibatch, the loss
//!   written inline, `backward_step`. The gap between the two is the Rust side's own cost
//!   (index shuffling, `index_select` of the minibatch, scalar read-backs for logging); what
//!   remains in `bare` is libtorch plus tch's thin FFI. `perf record` on this benchmark splits
//!   that further (docs/BENCHMARKS.md, section Learner).

use std::time::{Duration, Instant};

use criterion::{criterion_group, criterion_main, BenchmarkId, Criterion, Throughput};
use tch::nn::OptimizerConfig;
use tch::{nn, Kind, Reduction, Tensor};
use uavmeta_learner::progress::OnStep;
use uavmeta_learner::qnet::{QNetwork, QNetworkConfig};
use uavmeta_learner::train::{train, EvaluatePolicy, Rollouts, TrainOptions};
use uavmeta_learner::transitions::Transitions;
use uavmeta_proto::config::Config;
use uavmeta_proto::dataset::Transition;
use uavmeta_proto::method::Algo;
use uavmeta_proto::stats::PolicyMetrics;

const OBS: i64 = 12;
const ACTIONS: i64 = 50;
const ROWS: i64 = 4096;

struct NoEvaluation;

impl EvaluatePolicy for NoEvaluation {
    fn evaluate(&mut self, _q: &QNetwork) -> PolicyMetrics {
        PolicyMetrics::default()
    }

    fn rollouts(&mut self, _q: &QNetwork, _ask: Rollouts) -> Option<Vec<Transition>> {
        None
    }
}

fn dataset() -> Transitions {
    tch::manual_seed(0);
    let cpu = tch::Device::Cpu;
    Transitions {
        obs: Tensor::rand([ROWS, OBS], (Kind::Float, cpu)),
        actions: Tensor::randint(ACTIONS, [ROWS], (Kind::Int64, cpu)),
        rewards: -Tensor::rand([ROWS], (Kind::Float, cpu)),
        next_obs: Tensor::rand([ROWS, OBS], (Kind::Float, cpu)),
    }
}

fn config(batch: usize, steps: u64) -> Config {
    let overrides = [
        format!("learner.batch_size={batch}"),
        format!("learner.steps_per_epoch={steps}"),
        "learner.epochs=1".into(),
        // The value guard costs a forward pass over the whole dataset per epoch (4096 rows
        // here), not per step; with one epoch per timed call it would be charged to a handful
        // of steps.
        "learner.value_guard=0".into(),
    ];
    Config::from_toml_str("", "bench", &overrides).expect("valid overrides")
}

fn bench(c: &mut Criterion) {
    // One intra-op thread: the machine's two cores are shared, and libtorch's OpenMP workers
    // spin-waiting for a busy core make multi-threaded timings swing tenfold between runs.
    tch::set_num_threads(1);
    let data = dataset();
    let mut group = c.benchmark_group("cql_step");
    group.measurement_time(Duration::from_secs(8));
    group.throughput(Throughput::Elements(1));
    for batch in [64usize, 256] {
        group.bench_function(BenchmarkId::new("train", batch), |b| {
            b.iter_custom(|iters| {
                let cfg = config(batch, iters);
                let mut q =
                    QNetworkConfig::new(OBS as usize, ACTIONS as usize, &[256, 256]).init(0);
                let opts = TrainOptions {
                    algorithm: Algo::CQL,
                    config: &cfg,
                    seed: 0,
                    out_dir: None,
                    progress: false,
                    on_step: OnStep::default(),
                };
                let start = Instant::now();
                train(&mut q, &data, &opts, &mut NoEvaluation).expect("no outputs to fail");
                start.elapsed()
            })
        });
        group.bench_function(BenchmarkId::new("bare", batch), |b| {
            let q = QNetworkConfig::new(OBS as usize, ACTIONS as usize, &[256, 256]).init(0);
            let target = q.duplicate();
            let mut opt = nn::Adam::default().build(&q.vs, 1e-3).expect("Adam builds");
            let mb = data.select(&Tensor::arange(
                batch as i64,
                (Kind::Int64, tch::Device::Cpu),
            ));
            let a = mb.actions.unsqueeze(1);
            b.iter(|| {
                let q_all = q.forward(&mb.obs);
                let next = tch::no_grad(|| target.forward(&mb.next_obs).amax(-1, false));
                let y = (&mb.rewards + next * 0.99).detach();
                let q_sa = q_all.gather(1, &a, false).squeeze_dim(1);
                let td = q_sa.mse_loss(&y, Reduction::Mean);
                let cons = (q_all.logsumexp([-1i64], false) - &q_sa).mean(None);
                opt.backward_step(&(td * 0.5 + cons));
            })
        });
    }
    group.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
