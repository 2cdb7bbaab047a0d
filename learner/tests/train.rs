//! Offline training end to end on a synthetic contextual bandit the test can score exactly:
//! K = 1 (obs [x, y, A], 5 actions), the rewarded action is 1 when x < 5 and 3 otherwise.

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use tch::Tensor;
use uavmeta_learner::batch::Batch;
use uavmeta_learner::checkpoint;
use uavmeta_learner::progress::OnStep;
use uavmeta_learner::qnet::{QNetwork, QNetworkConfig};
use uavmeta_learner::train::{train, EpochRow, EvaluatePolicy, TrainOptions};
use uavmeta_learner::train_population::{train_population, Member, PopulationOptions};
use uavmeta_proto::config::{Config, Loss};
use uavmeta_proto::dataset::Transition;
use uavmeta_proto::stats::{EpisodeMetrics, PolicyMetrics};

fn best_action(x: u16) -> u16 {
    if x < 5 {
        1
    } else {
        3
    }
}

fn dataset(n: usize) -> Vec<Transition> {
    dataset_seeded(n, 1)
}

fn dataset_seeded(n: usize, seed: u64) -> Vec<Transition> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    (0..n)
        .map(|i| {
            let obs = vec![rng.random_range(0..10), rng.random_range(0..10), 1];
            let action = rng.random_range(0..5u16);
            let reward = if action == best_action(obs[0]) {
                1.0
            } else {
                0.0
            };
            let next_obs = vec![rng.random_range(0..10), rng.random_range(0..10), 1];
            Transition {
                task: 0,
                actor: 0,
                episode: 0,
                step: i as u32,
                seq: i as u64,
                obs,
                action,
                reward,
                next_obs,
                truncated: false,
            }
        })
        .collect()
}

/// "Return" = share of the ten x positions where the greedy action is the rewarded one.
struct Exact;

impl EvaluatePolicy for Exact {
    fn evaluate(&mut self, q: &QNetwork) -> PolicyMetrics {
        let episodes: Vec<EpisodeMetrics> = (0..10u16)
            .map(|x| {
                let obs = Tensor::from_slice(&[x as f32 / 9.0, 0.5, 0.01]).view([1, 3]);
                let a = q.greedy(&obs).int64_value(&[0]) as u16;
                EpisodeMetrics {
                    ret: (a == best_action(x)) as u8 as f64,
                    ..Default::default()
                }
            })
            .collect();
        PolicyMetrics::from_episodes(&episodes)
    }

    fn measure(&mut self, q: &QNetwork) -> Option<PolicyMetrics> {
        Some(self.evaluate(q))
    }
}

fn config() -> Config {
    let text = "[world]\ndevices = 1\n[learner]\nhidden = [32, 32]\ngamma = 0.0\nreward_scale = 1.0\nepochs = 30\nbatch = 32\nlr = 3e-3\n";
    Config::from_toml_str(text, "bandit.toml", &[]).unwrap()
}

#[test]
fn cql_learns_the_bandit_and_writes_its_outputs() {
    // Small networks: one libtorch thread avoids OpenMP spin-waiting on a shared machine.
    tch::set_num_threads(1);
    let cfg = config();
    let data = Batch::new(&dataset(400), &cfg.world, cfg.learner.reward_scale).unwrap();
    let dir = tempfile::tempdir().unwrap();
    let run = |out: Option<&std::path::Path>| {
        let mut q = QNetworkConfig::new(3, 5, &cfg.learner.hidden).init(0);
        let opts = TrainOptions {
            algorithm: Loss::Cql,
            config: &cfg,
            seed: 4,
            out_dir: out,
            progress: false,
            on_step: OnStep::default(),
        };
        train(&mut q, &data, &opts, &mut Exact).unwrap()
    };
    let rows = run(Some(dir.path()));
    assert_eq!(rows.len(), 30);
    // 400 shots / batch 32 = 13 steps per epoch.
    assert_eq!(rows[29].steps, 30 * 13);
    let first = rows[0].policy.ret.mean;
    let last = rows[29].policy.ret.mean;
    assert_eq!(
        last, 1.0,
        "the greedy action is right at every x (first epoch: {first})"
    );
    // With gamma = 0, Q(s, a_data) regresses onto r in [0, 1], so the greedy value stays there.
    assert!(
        rows[29].mean_q > 0.5 && rows[29].mean_q < 1.5,
        "{}",
        rows[29].mean_q
    );

    let csv = std::fs::read_to_string(dir.path().join("train.csv")).unwrap();
    assert_eq!(csv.lines().count(), 31);
    assert!(csv.starts_with("epoch,steps,td_loss,conservative_loss,mean_q,return"));
    let (q, meta) = checkpoint::load(&dir.path().join("final"), &cfg).unwrap();
    assert_eq!((meta.algorithm.as_str(), meta.epoch), ("cql", 30));
    assert_eq!(Exact.evaluate(&q).ret.mean, 1.0);

    // Same seed, same run.
    let again = run(None);
    assert_eq!(
        again.iter().map(|r| r.td_loss).collect::<Vec<_>>(),
        rows.iter().map(|r| r.td_loss).collect::<Vec<_>>()
    );
}

/// `train` alone: the network it ends with and its rows.
fn alone(
    cfg: &Config,
    algorithm: Loss,
    init: u64,
    data: &Batch,
    seed: u64,
) -> (QNetwork, Vec<EpochRow>) {
    alone_scored(cfg, algorithm, init, data, seed, &mut Exact)
}

/// [`alone`] scored by `evaluator`.
fn alone_scored(
    cfg: &Config,
    algorithm: Loss,
    init: u64,
    data: &Batch,
    seed: u64,
    evaluator: &mut dyn EvaluatePolicy,
) -> (QNetwork, Vec<EpochRow>) {
    let init = QNetworkConfig::new(3, 5, &cfg.learner.hidden).init(init);
    trained(cfg, algorithm, init, data, seed, None, evaluator)
}

/// `train` of `q` on `data`, writing into `out_dir` if given: the network it ends with and its
/// rows.
fn trained(
    cfg: &Config,
    algorithm: Loss,
    mut q: QNetwork,
    data: &Batch,
    seed: u64,
    out_dir: Option<&std::path::Path>,
    evaluator: &mut dyn EvaluatePolicy,
) -> (QNetwork, Vec<EpochRow>) {
    let opts = TrainOptions {
        algorithm,
        config: cfg,
        seed,
        out_dir,
        progress: false,
        on_step: OnStep::default(),
    };
    let rows = train(&mut q, data, &opts, evaluator).unwrap();
    (q, rows)
}

/// `train_population` over members `(init seed, data, minibatch seed)`.
fn together(
    cfg: &Config,
    algorithm: Loss,
    members: &[(u64, &Batch, u64)],
) -> Vec<(QNetwork, Vec<EpochRow>)> {
    let mut evaluators: Vec<Exact> = members.iter().map(|_| Exact).collect();
    let members = members
        .iter()
        .zip(&mut evaluators)
        .map(|(&(init, data, seed), evaluator)| Member {
            init: QNetworkConfig::new(3, 5, &cfg.learner.hidden).init(init),
            data,
            seed,
            evaluator,
            out_dir: None,
        })
        .collect();
    let opts = PopulationOptions {
        algorithm,
        config: cfg,
        device: tch::Device::Cpu,
        on_step: OnStep::default(),
    };
    train_population(members, &opts)
        .unwrap()
        .into_iter()
        .map(|t| (t.q, t.rows))
        .collect()
}

/// A row without its wall-clock seconds.
fn figures(rows: &[EpochRow]) -> Vec<(usize, usize, f64, f64, f64, f64)> {
    rows.iter()
        .map(|r| {
            (
                r.epoch,
                r.steps,
                r.td_loss,
                r.conservative_loss,
                r.mean_q,
                r.policy.ret.mean,
            )
        })
        .collect()
}

/// Training sets of 400 transitions, one per data seed.
fn batches(cfg: &Config, seeds: std::ops::RangeInclusive<u64>) -> Vec<Batch> {
    seeds
        .map(|s| {
            Batch::new(
                &dataset_seeded(400, s),
                &cfg.world,
                cfg.learner.reward_scale,
            )
            .unwrap()
        })
        .collect()
}

#[test]
fn a_population_of_one_is_train_bit_for_bit() {
    tch::set_num_threads(1);
    let mut cfg = config();
    cfg.learner.epochs = 8;
    let data = Batch::new(&dataset(400), &cfg.world, cfg.learner.reward_scale).unwrap();
    for (algorithm, extra) in [(Loss::Cql, false), (Loss::Dqn, true)] {
        cfg.learner.double_dqn = extra;
        cfg.learner.huber = extra;
        for decay in [0.0, 0.9] {
            cfg.learner.average_decay = decay;
            let (q, rows) = alone(&cfg, algorithm, 3, &data, 5);
            let one = together(&cfg, algorithm, &[(3, &data, 5)]);
            assert_eq!(figures(&one[0].1), figures(&rows), "{algorithm} {decay}");
            assert_eq!(one[0].0.max_abs_difference(&q), 0.0, "{algorithm} {decay}");
        }
    }
}

/// Keeps a copy of every network it is asked to score.
struct Recorder(Vec<QNetwork>);

impl EvaluatePolicy for Recorder {
    fn evaluate(&mut self, q: &QNetwork) -> PolicyMetrics {
        self.0.push(q.duplicate());
        Exact.evaluate(q)
    }

    /// Scores without recording: a measurement is not an epoch.
    fn measure(&mut self, q: &QNetwork) -> Option<PolicyMetrics> {
        Some(Exact.evaluate(q))
    }
}

/// `learner.average_decay` = d publishes, after epoch t, sum_k d^(t-k) Q_k / sum_k d^(t-k) over
/// the networks Q_1..Q_t the same run trains without averaging (the gradient steps do not see
/// the average), with no weight on the init; the returned network is the last average.
#[test]
fn averaging_publishes_the_bias_corrected_average_of_the_epochs_networks() {
    tch::set_num_threads(1);
    let mut cfg = config();
    cfg.learner.epochs = 5;
    let data = Batch::new(&dataset(400), &cfg.world, cfg.learner.reward_scale).unwrap();
    let run = |cfg: &Config| {
        let mut recorder = Recorder(Vec::new());
        let (q, _) = alone_scored(cfg, Loss::Cql, 2, &data, 6, &mut recorder);
        (q, recorder.0)
    };
    let (last, raw) = run(&cfg);
    let d = 0.8;
    cfg.learner.average_decay = d;
    let (published_last, published) = run(&cfg);
    assert_eq!(published.len(), 5);
    for t in 1..=5 {
        let weights: Vec<f64> = (1..=t).map(|k| d.powi((t - k) as i32)).collect();
        let total: f64 = weights.iter().sum();
        let expected: Vec<Tensor> = (0..raw[0].parameters().len())
            .map(|p| {
                (0..t)
                    .map(|k| {
                        raw[k].parameters()[p].to_kind(tch::Kind::Double) * (weights[k] / total)
                    })
                    .reduce(|a, b| a + b)
                    .unwrap()
            })
            .collect();
        let gap = published[t - 1]
            .parameters()
            .iter()
            .zip(&expected)
            .map(|(a, b)| {
                (a.to_kind(tch::Kind::Double) - b)
                    .abs()
                    .max()
                    .double_value(&[])
            })
            .fold(0.0, f64::max);
        assert!(
            gap < 1e-5,
            "epoch {t}: the published network is {gap} from the average"
        );
    }
    // The first epoch's average is that epoch's network itself: the init has no weight.
    assert_eq!(published[0].max_abs_difference(&raw[0]), 0.0);
    assert!(
        published[4].max_abs_difference(&raw[4]) > 1e-4,
        "the average is not the last network"
    );
    assert_eq!(published_last.max_abs_difference(&published[4]), 0.0);
    assert_eq!(last.max_abs_difference(&raw[4]), 0.0);
}

#[test]
fn each_member_of_a_population_follows_its_own_separate_run() {
    tch::set_num_threads(1);
    let mut cfg = config();
    cfg.learner.epochs = 6;
    cfg.learner.double_dqn = true;
    // Other data (its own draw), another init and another minibatch order per member.
    let data = batches(&cfg, 1..=3);
    let members = [(0, &data[0], 10), (1, &data[1], 11), (2, &data[2], 12)];
    for algorithm in [Loss::Cql, Loss::Dqn] {
        let pop = together(&cfg, algorithm, &members);
        for (i, &(init, d, seed)) in members.iter().enumerate() {
            let (q, rows) = alone(&cfg, algorithm, init, d, seed);
            let gap = pop[i].0.max_abs_difference(&q);
            eprintln!("{algorithm} member {i}: largest weight difference {gap:e}");
            assert!(
                gap < 1e-4,
                "{algorithm} member {i} drifted {gap} from its separate run"
            );
            for (a, b) in figures(&pop[i].1).iter().zip(figures(&rows)) {
                assert_eq!((a.0, a.1), (b.0, b.1));
                assert!(
                    (a.2 - b.2).abs() < 1e-4 * b.2.abs().max(1.0),
                    "{algorithm} member {i}: {a:?} vs {b:?}"
                );
            }
        }
        // Without the others, member 1 is the same run: nothing passes between members.
        let pair = together(&cfg, algorithm, &members[1..2]);
        assert!(pair[0].0.max_abs_difference(&pop[1].0) < 1e-4);
    }
}

#[test]
fn a_member_stopped_by_the_value_guard_keeps_its_network_as_train_does() {
    tch::set_num_threads(1);
    let mut cfg = config();
    cfg.learner.epochs = 12;
    cfg.learner.gamma = 0.5;
    cfg.learner.value_guard = 0.01;
    let data = batches(&cfg, 1..=2);
    let members = [(0, &data[0], 10), (1, &data[1], 11)];
    let pop = together(&cfg, Loss::Cql, &members);
    let mut stopped = 0;
    for (i, &(init, d, seed)) in members.iter().enumerate() {
        let (q, rows) = alone(&cfg, Loss::Cql, init, d, seed);
        // The guard stops the run: its step count stops growing before the last epoch.
        stopped += usize::from(rows[11].steps < 12 * 13);
        assert_eq!(
            pop[i].1.iter().map(|r| r.steps).collect::<Vec<_>>(),
            rows.iter().map(|r| r.steps).collect::<Vec<_>>(),
            "member {i} stopped at another epoch than its separate run"
        );
        assert!(pop[i].0.max_abs_difference(&q) < 1e-4, "member {i}");
    }
    assert!(
        stopped > 0,
        "the guard never stopped a run: the test sees nothing"
    );
}

#[test]
fn without_the_value_guard_every_epoch_trains() {
    tch::set_num_threads(1);
    let mut cfg = config();
    cfg.learner.epochs = 4;
    cfg.learner.value_guard = 0.0;
    let data = Batch::new(&dataset(400), &cfg.world, cfg.learner.reward_scale).unwrap();
    let (_, rows) = alone(&cfg, Loss::Cql, 0, &data, 1);
    assert_eq!(
        rows.iter().map(|r| r.steps).collect::<Vec<_>>(),
        vec![13, 26, 39, 52]
    );
}

#[test]
fn members_of_other_shapes_are_refused_by_number() {
    let cfg = config();
    let big = Batch::new(&dataset(400), &cfg.world, cfg.learner.reward_scale).unwrap();
    let small = Batch::new(&dataset(100), &cfg.world, cfg.learner.reward_scale).unwrap();
    let mut evaluators = [Exact, Exact];
    let members = [(0u64, &big), (1, &small)]
        .into_iter()
        .zip(&mut evaluators)
        .map(|((init, data), evaluator)| Member {
            init: QNetworkConfig::new(3, 5, &cfg.learner.hidden).init(init),
            data,
            seed: 0,
            evaluator,
            out_dir: None,
        })
        .collect();
    let opts = PopulationOptions {
        algorithm: Loss::Cql,
        config: &cfg,
        device: tch::Device::Cpu,
        on_step: OnStep::default(),
    };
    let error = train_population(members, &opts).err().unwrap().to_string();
    assert!(
        error.contains("population member 1")
            && error.contains("4 steps per epoch")
            && error.contains("13 steps"),
        "{error}"
    );
}

/// `select.csv`'s rows: (epoch, FQE value, measured return, kept).
fn selection_rows(dir: &std::path::Path) -> Vec<(usize, f64, f64, bool)> {
    let text = std::fs::read_to_string(dir.join("select.csv")).unwrap();
    let mut lines = text.lines();
    assert_eq!(lines.next(), Some("epoch,fqe_value,return,kept"));
    lines
        .map(|line| {
            let f: Vec<&str> = line.split(',').collect();
            (
                f[0].parse().unwrap(),
                f[1].parse().unwrap(),
                f[2].parse().unwrap(),
                f[3] == "1",
            )
        })
        .collect()
}

/// A run from `init` writing into `dir`; also the networks `train` gave its evaluator as
/// epochs' published ones.
fn selected_run(
    cfg: &Config,
    algorithm: Loss,
    init: &QNetwork,
    data: &Batch,
    dir: &std::path::Path,
) -> (QNetwork, Vec<EpochRow>, Vec<QNetwork>) {
    let mut recorder = Recorder(Vec::new());
    let (q, rows) = trained(
        cfg,
        algorithm,
        init.duplicate(),
        data,
        2,
        Some(dir),
        &mut recorder,
    );
    (q, rows, recorder.0)
}

#[test]
fn the_fqe_selection_keeps_the_best_scored_network_and_catches_a_drift() {
    tch::set_num_threads(1);
    let mut cfg = config();
    cfg.learner.select_every = 5;
    cfg.learner.fqe_steps = 600;
    let data = Batch::new(&dataset(400), &cfg.world, cfg.learner.reward_scale).unwrap();

    // From a random init the trained networks score higher than the init (with gamma = 0 FQE
    // regresses the reward of the policy's own action), so the run keeps a trained one.
    let random = QNetworkConfig::new(3, 5, &cfg.learner.hidden).init(0);
    let dir = tempfile::tempdir().unwrap();
    let (learned, rows, evaluated) = selected_run(&cfg, Loss::Cql, &random, &data, dir.path());
    // One evaluation an epoch, of what the run publishes: the candidates' scoring is not seen
    // by the evaluator as epochs (the launch's counts them and announces a checkpoint each).
    assert_eq!(evaluated.len(), cfg.learner.epochs);
    let scored = selection_rows(dir.path());
    assert_eq!(
        scored.iter().map(|r| r.0).collect::<Vec<_>>(),
        [0, 5, 10, 15, 20, 25, 30]
    );
    // The first of the highest scores (two networks with the same greedy actions tie).
    let best = scored
        .iter()
        .fold(&scored[0], |best, r| if r.1 > best.1 { r } else { best });
    assert!(best.0 > 0 && best.2 == 1.0, "kept {best:?} of {scored:?}");
    assert_eq!(Exact.evaluate(&learned).ret.mean, best.2);
    assert_eq!(rows.last().unwrap().policy.ret.mean, best.2);
    // `kept` marks each new best in order; the last one marked is the best.
    assert_eq!(scored.iter().rev().find(|r| r.3).unwrap().0, best.0);

    // From that network, a rate far too high wrecks the policy; the selection keeps a network
    // from before the wreck (the value guard off, so the wreck is not stopped by it first).
    cfg.learner.lr = 3.0;
    cfg.learner.value_guard = 0.0;
    let dir = tempfile::tempdir().unwrap();
    let (kept, _, _) = selected_run(&cfg, Loss::Dqn, &learned, &data, dir.path());
    let scored = selection_rows(dir.path());
    let wrecked = scored.last().unwrap().2;
    assert!(
        wrecked < 1.0,
        "the rate did not wreck the policy: {scored:?}"
    );
    assert_eq!(Exact.evaluate(&kept).ret.mean, 1.0, "{scored:?}");

    // A period longer than the run still scores its last epoch beside the init.
    cfg.learner.select_every = 1000;
    let dir = tempfile::tempdir().unwrap();
    selected_run(&cfg, Loss::Dqn, &learned, &data, dir.path());
    let epochs: Vec<usize> = selection_rows(dir.path()).iter().map(|r| r.0).collect();
    assert_eq!(epochs, [0, cfg.learner.epochs]);
}

/// The largest distance of any weight of `q` from the same weight of `init`.
fn distance(q: &QNetwork, init: &QNetwork) -> f64 {
    q.max_abs_difference(init)
}

#[test]
fn the_init_penalty_holds_a_run_near_its_init() {
    tch::set_num_threads(1);
    let mut cfg = config();
    let data = Batch::new(&dataset(400), &cfg.world, cfg.learner.reward_scale).unwrap();
    let init = QNetworkConfig::new(3, 5, &cfg.learner.hidden).init(0);
    let (free, _) = alone(&cfg, Loss::Cql, 0, &data, 4);
    cfg.learner.init_penalty = 10.0;
    let (held, _) = alone(&cfg, Loss::Cql, 0, &data, 4);
    let (d_free, d_held) = (distance(&free, &init), distance(&held, &init));
    assert!(
        d_held < 0.25 * d_free,
        "held {d_held} against free {d_free}: the penalty did not hold the run"
    );
}
