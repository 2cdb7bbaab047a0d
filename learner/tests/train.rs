//! Offline training end to end on a synthetic contextual bandit the test can score exactly:
//! K = 1 (obs [x, y, A], 5 actions), the rewarded action is 1 when x < 5 and 3 otherwise.

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use tch::Tensor;
use uavmeta_learner::checkpoint;
use uavmeta_learner::progress::OnStep;
use uavmeta_learner::qnet::{QNetwork, QNetworkConfig};
use uavmeta_learner::train::{train, EpochRow, EvaluatePolicy, Rollouts, TrainOptions};
use uavmeta_learner::transitions::Transitions;
use uavmeta_proto::config::Config;
use uavmeta_proto::dataset::Transition;
use uavmeta_proto::method::Algo;
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

    fn rollouts(&mut self, _q: &QNetwork, _ask: Rollouts) -> Option<Vec<Transition>> {
        None
    }
}

fn config() -> Config {
    let text = "[world]\ndevices = 1\n[learner]\nhidden = [32, 32]\ngamma = 0.0\nreward_scale = 1.0\nepochs = 30\nbatch_size = 32\nlr = 3e-3\n";
    Config::from_toml_str(text, "bandit.toml", &[]).unwrap()
}

#[test]
fn cql_learns_the_bandit_and_writes_its_outputs() {
    // Small networks: one libtorch thread avoids OpenMP spin-waiting on a shared machine.
    tch::set_num_threads(1);
    let cfg = config();
    let data = Transitions::new(&dataset(400), &cfg.world, cfg.learner.reward_scale).unwrap();
    let dir = tempfile::tempdir().unwrap();
    let run = |out: Option<&std::path::Path>| {
        let mut q = QNetworkConfig::new(3, 5, &cfg.learner.hidden).init(0);
        let opts = TrainOptions {
            algorithm: Algo::CQL,
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
    algorithm: Algo,
    init: u64,
    data: &Transitions,
    seed: u64,
) -> (QNetwork, Vec<EpochRow>) {
    alone_scored(cfg, algorithm, init, data, seed, &mut Exact)
}

/// [`alone`] scored by `evaluator`.
fn alone_scored(
    cfg: &Config,
    algorithm: Algo,
    init: u64,
    data: &Transitions,
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
    algorithm: Algo,
    mut q: QNetwork,
    data: &Transitions,
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

/// Training sets of 400 transitions, one per data seed.
fn batches(cfg: &Config, seeds: std::ops::RangeInclusive<u64>) -> Vec<Transitions> {
    seeds
        .map(|s| {
            Transitions::new(
                &dataset_seeded(400, s),
                &cfg.world,
                cfg.learner.reward_scale,
            )
            .unwrap()
        })
        .collect()
}

/// Keeps a copy of every network it is asked to score.
struct Recorder(Vec<QNetwork>);

impl EvaluatePolicy for Recorder {
    fn evaluate(&mut self, q: &QNetwork) -> PolicyMetrics {
        self.0.push(q.duplicate());
        Exact.evaluate(q)
    }

    fn rollouts(&mut self, _q: &QNetwork, _ask: Rollouts) -> Option<Vec<Transition>> {
        None
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
    let data = Transitions::new(&dataset(400), &cfg.world, cfg.learner.reward_scale).unwrap();
    let run = |cfg: &Config| {
        let mut recorder = Recorder(Vec::new());
        let (q, _) = alone_scored(cfg, Algo::CQL, 2, &data, 6, &mut recorder);
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

/// A run the value guard stops keeps training no more: its step count stops growing, the epoch
/// it trips at and every later row score the last good epoch's network (evaluated once, when it
/// was trained: no evaluation follows the stop), and it ends with that network.
#[test]
fn the_value_guard_stops_a_run_and_keeps_its_last_good_network() {
    tch::set_num_threads(1);
    let mut cfg = config();
    cfg.learner.epochs = 12;
    cfg.learner.gamma = 0.5;
    cfg.learner.value_guard = 0.01;
    let mut stopped = 0;
    for (i, data) in batches(&cfg, 1..=2).iter().enumerate() {
        let mut recorder = Recorder(Vec::new());
        let (q, rows) = alone_scored(
            &cfg,
            Algo::CQL,
            i as u64,
            data,
            10 + i as u64,
            &mut recorder,
        );
        let Some(last) = rows.iter().position(|r| r.steps < r.epoch * 13) else {
            continue;
        };
        stopped += 1;
        // Epoch `last` (0-based) is the first that did not train: it and every later row repeat
        // the steps of the row before it, which tripped the guard; from that row on each scores
        // the network of the epoch before the trip, the last one evaluated.
        let tripped = last - 1;
        assert!(tripped > 0, "run {i} tripped at its first epoch");
        for row in &rows[last..] {
            assert_eq!(row.steps, rows[tripped].steps, "run {i}");
        }
        for row in &rows[tripped..] {
            assert_eq!(row.network_epoch, tripped, "run {i}");
            assert_eq!(row.policy, rows[tripped - 1].policy, "run {i}");
        }
        assert_eq!(
            recorder.0.len(),
            tripped,
            "run {i}: one evaluation per trained network"
        );
        assert_eq!(
            q.max_abs_difference(&recorder.0[tripped - 1]),
            0.0,
            "run {i}"
        );
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
    let data = Transitions::new(&dataset(400), &cfg.world, cfg.learner.reward_scale).unwrap();
    let (_, rows) = alone(&cfg, Algo::CQL, 0, &data, 1);
    assert_eq!(
        rows.iter().map(|r| r.steps).collect::<Vec<_>>(),
        vec![13, 26, 39, 52]
    );
}

/// Behaviour cloning imitates the logged actions and ignores the rewards: on data whose behaviour
/// policy takes the rewarded action 80% of the time but whose rewards are all 0, BC's greedy
/// action is the behaviour's most frequent one on every x, and the value guard (a Q-learning
/// check) never stops it.
#[test]
fn behaviour_cloning_takes_the_data_s_most_frequent_action_whatever_the_rewards() {
    tch::set_num_threads(1);
    let mut cfg = config();
    cfg.learner.value_guard = 0.01;
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    let data: Vec<Transition> = dataset(400)
        .into_iter()
        .map(|t| {
            let action = match rng.random_bool(0.8) {
                true => best_action(t.obs[0]),
                false => rng.random_range(0..5u16),
            };
            Transition {
                action,
                reward: 0.0,
                ..t
            }
        })
        .collect();
    let data = Transitions::new(&data, &cfg.world, cfg.learner.reward_scale).unwrap();
    let (_, rows) = alone(&cfg, "bc".parse::<Algo>().unwrap(), 0, &data, 4);
    assert_eq!(
        rows.last().unwrap().policy.ret.mean,
        1.0,
        "{:?}",
        rows.last()
    );
    assert_eq!(
        rows.last().unwrap().steps,
        cfg.learner.epochs * 13,
        "BC was stopped"
    );
}

/// The bandit's exact evaluation, counting its calls, and a model whose rollouts are the
/// bandit's transitions (or none).
struct Modelled {
    evaluations: usize,
    rollouts: usize,
    model: bool,
}

impl Modelled {
    fn new(model: bool) -> Self {
        Self {
            evaluations: 0,
            rollouts: 0,
            model,
        }
    }
}

impl EvaluatePolicy for Modelled {
    fn evaluate(&mut self, q: &QNetwork) -> PolicyMetrics {
        self.evaluations += 1;
        Exact.evaluate(q)
    }

    fn rollouts(&mut self, _q: &QNetwork, ask: Rollouts) -> Option<Vec<Transition>> {
        self.rollouts += 1;
        self.model.then(|| dataset_seeded(ask.rows + 100, ask.seed))
    }
}

/// A named algorithm trains on the shots alone and reports its last epoch's network: it never
/// asks for the model's rollouts, every epoch scores that epoch's network once, and the last
/// row, the returned network and the `final` checkpoint are the last epoch's. `dyna-cql` draws
/// model rows every epoch, and without a model it is `cql` to the bit.
#[test]
fn named_algorithms_read_the_shots_alone_and_dyna_cql_adds_model_rows() {
    tch::set_num_threads(1);
    let mut cfg = config();
    cfg.learner.model_rows = 200;
    let data = Transitions::new(&dataset(400), &cfg.world, cfg.learner.reward_scale).unwrap();
    let start = QNetworkConfig::new(3, 5, &cfg.learner.hidden).init(0);
    let probe = Tensor::from_slice(&[0.3f32, 0.5, 0.01, 0.8, 0.1, 0.01]).view([2, 3]);
    let run = |algo: &str, model: bool| {
        let dir = tempfile::tempdir().unwrap();
        let mut evaluator = Modelled::new(model);
        let (q, rows) = trained(
            &cfg,
            algo.parse::<Algo>().unwrap(),
            start.duplicate(),
            &data,
            4,
            Some(dir.path()),
            &mut evaluator,
        );
        let kept = checkpoint::load(&dir.path().join("final"), &cfg).unwrap().0;
        assert!(kept
            .forward(&probe)
            .allclose(&q.forward(&probe), 0.0, 0.0, false));
        (rows, q.forward(&probe), evaluator)
    };
    let epochs = cfg.learner.epochs;
    for algo in ["cql", "dqn", "bc", "bcq"] {
        let (rows, _, evaluator) = run(algo, true);
        assert_eq!(
            (evaluator.rollouts, evaluator.evaluations),
            (0, epochs),
            "{algo}"
        );
        for (i, row) in rows.iter().enumerate() {
            assert_eq!((row.epoch, row.network_epoch), (i + 1, i + 1), "{algo}");
        }
        assert_eq!(rows.last().unwrap().kept(), format!("epoch {epochs}"));
    }
    let (cql, cql_q, _) = run("cql", true);
    let (dyna, dyna_q, evaluator) = run("dyna-cql", true);
    assert_eq!(
        (evaluator.rollouts, evaluator.evaluations),
        (epochs, epochs)
    );
    assert!(
        dyna[0].steps > cql[0].steps,
        "model rows lengthen the epoch"
    );
    assert!(!dyna_q.allclose(&cql_q, 1e-6, 1e-6, false));
    let (alone, alone_q, evaluator) = run("dyna-cql", false);
    assert_eq!(
        evaluator.rollouts, 1,
        "asked once, then trained on the shots alone"
    );
    assert!(alone_q.allclose(&cql_q, 0.0, 0.0, false));
    for (a, b) in alone.iter().zip(&cql) {
        assert_eq!(
            (a.td_loss, a.policy, a.steps),
            (b.td_loss, b.policy, b.steps)
        );
    }
}
