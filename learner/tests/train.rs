//! Offline training end to end on a synthetic contextual bandit the test can score exactly:
//! K = 1 (obs [x, y, A], 5 actions), the rewarded action is 1 when x < 5 and 3 otherwise.

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use tch::Tensor;
use uavmeta_learner::checkpoint;
use uavmeta_learner::progress::OnStep;
use uavmeta_learner::qnet::{QNetwork, QNetworkConfig};
use uavmeta_learner::train::{train, EpochRow, EvaluatePolicy, TrainOptions};
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

    /// No shots identify this world: runs keep their last network.
    fn judge(&mut self, _q: &QNetwork) -> Option<f64> {
        None
    }

    fn rollouts(&mut self, _q: &QNetwork, _eps: f64, _seed: u64) -> Option<Vec<Transition>> {
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

    fn judge(&mut self, _q: &QNetwork) -> Option<f64> {
        None
    }

    fn rollouts(&mut self, _q: &QNetwork, _eps: f64, _seed: u64) -> Option<Vec<Transition>> {
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

/// A run the value guard stops keeps training no more: its step count stops growing, its later
/// rows repeat the last trained one, and it ends with the network of its last good epoch.
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
        // the row before it, and the network is the one that row published.
        for row in &rows[last..] {
            assert_eq!(row.steps, rows[last - 1].steps, "run {i}");
            assert_eq!(row.policy, rows[last - 1].policy, "run {i}");
        }
        assert_eq!(q.max_abs_difference(&recorder.0[last - 1]), 0.0, "run {i}");
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

/// The bandit's exact evaluation, and a judge that scores a network by `judge` of its exact
/// return: the world a run's shots identify, here as right (identity) or as wrong as can be.
struct Judged(fn(f64) -> f64);

impl EvaluatePolicy for Judged {
    fn evaluate(&mut self, q: &QNetwork) -> PolicyMetrics {
        Exact.evaluate(q)
    }

    fn judge(&mut self, q: &QNetwork) -> Option<f64> {
        Some(self.0(Exact.evaluate(q).ret.mean))
    }

    fn rollouts(&mut self, _q: &QNetwork, _eps: f64, _seed: u64) -> Option<Vec<Transition>> {
        None
    }
}

#[test]
fn a_run_keeps_the_candidate_its_judge_scores_best_and_only_with_a_judge() {
    tch::set_num_threads(1);
    let mut cfg = config();
    cfg.learner.select_every = 10;
    let data = Transitions::new(&dataset(400), &cfg.world, cfg.learner.reward_scale).unwrap();
    let start = QNetworkConfig::new(3, 5, &cfg.learner.hidden).init(0);
    let run = |cfg: &Config, evaluator: &mut dyn EvaluatePolicy| {
        let dir = tempfile::tempdir().unwrap();
        let (q, rows) = trained(
            cfg,
            Algo::CQL,
            start.duplicate(),
            &data,
            4,
            Some(dir.path()),
            evaluator,
        );
        let csv = std::fs::read_to_string(dir.path().join("train.csv")).unwrap();
        let kept = checkpoint::load(&dir.path().join("final"), cfg).unwrap().0;
        assert_eq!(
            Exact.evaluate(&kept),
            rows[29].policy,
            "the checkpoint is the kept network"
        );
        (rows, csv, q)
    };
    // The candidates: the start and epochs 10, 20, 30, as the run without selection scores them.
    let (plain, _, _) = run(&cfg, &mut Exact);
    let start_return = Exact.evaluate(&start).ret.mean;
    let returns = [
        start_return,
        plain[9].policy.ret.mean,
        plain[19].policy.ret.mean,
        plain[29].policy.ret.mean,
    ];
    assert!(start_return < 1.0 && returns[3] == 1.0, "{returns:?}");

    // A judge that is right keeps a best candidate; one that is wrong keeps the worst, the
    // earliest of equals, and the last row scores it.
    let (right, csv, _) = run(&cfg, &mut Judged(|r| r));
    assert_eq!(right[29].policy.ret.mean, 1.0);
    let (wrong, _, q) = run(&cfg, &mut Judged(|r| -r));
    let worst = returns.iter().copied().fold(f64::INFINITY, f64::min);
    let earliest = returns.iter().position(|&r| r == worst).unwrap() * 10;
    assert_eq!(wrong[29].network_epoch, earliest);
    assert_eq!(wrong[29].policy.ret.mean, worst);
    assert_eq!(
        Exact.evaluate(&q).ret.mean,
        worst,
        "the returned network is the kept one"
    );
    // Training itself is the same run: only the last row and the kept network differ.
    assert_eq!(wrong[28].policy, plain[28].policy);
    assert_eq!(wrong[29].td_loss, plain[29].td_loss);

    // train.csv: the model's return at the candidates' epochs only.
    let header: Vec<&str> = csv.lines().next().unwrap().split(',').collect();
    let column = header.iter().position(|&c| c == "model_return").unwrap();
    let scored: Vec<usize> = csv
        .lines()
        .skip(1)
        .enumerate()
        .filter(|(_, line)| !line.split(',').nth(column).unwrap().is_empty())
        .map(|(i, _)| i + 1)
        .collect();
    assert_eq!(scored, [10, 20, 30]);

    // Without a judge (`Exact`), or with `select_every = 0`, the run keeps its last network.
    assert_eq!(plain[29].network_epoch, 30);
    cfg.learner.select_every = 0;
    let (off, _, _) = run(&cfg, &mut Judged(|r| -r));
    assert_eq!(
        (off[29].network_epoch, off[29].policy),
        (30, plain[29].policy)
    );
}

/// A judge that scores its `peak`-th call best (the start's is call 0, then the candidates in
/// the order they are offered), and a model whose rollouts are the bandit's transitions.
struct Peaked {
    calls: usize,
    peak: usize,
    rollouts: usize,
}

impl EvaluatePolicy for Peaked {
    fn evaluate(&mut self, q: &QNetwork) -> PolicyMetrics {
        Exact.evaluate(q)
    }

    fn judge(&mut self, _q: &QNetwork) -> Option<f64> {
        self.calls += 1;
        Some(-(self.calls as f64 - 1.0 - self.peak as f64).abs())
    }

    fn rollouts(&mut self, _q: &QNetwork, _eps: f64, seed: u64) -> Option<Vec<Transition>> {
        self.rollouts += 1;
        Some(dataset_seeded(300, seed))
    }
}

#[test]
fn the_model_twin_trains_on_model_rows_and_its_networks_are_candidates() {
    tch::set_num_threads(1);
    let mut cfg = config();
    cfg.learner.select_every = 10;
    cfg.learner.model_rows = 200;
    let data = Transitions::new(&dataset(400), &cfg.world, cfg.learner.reward_scale).unwrap();
    let start = QNetworkConfig::new(3, 5, &cfg.learner.hidden).init(0);
    let probe = Tensor::from_slice(&[0.3f32, 0.5, 0.01, 0.8, 0.1, 0.01]).view([2, 3]);
    let run = |cfg: &Config, peak: usize| {
        let dir = tempfile::tempdir().unwrap();
        let mut judge = Peaked {
            calls: 0,
            peak,
            rollouts: 0,
        };
        let (q, rows) = trained(
            cfg,
            Algo::CQL,
            start.duplicate(),
            &data,
            4,
            Some(dir.path()),
            &mut judge,
        );
        let csv = std::fs::read_to_string(dir.path().join("train.csv")).unwrap();
        let last = csv.lines().last().unwrap().to_string();
        (rows, last, q.forward(&probe), judge)
    };
    // Candidates: the start, the twin's epochs 10, 20, 30, then the run's own.
    let (twin, last, twin_q, judge) = run(&cfg, 2);
    assert_eq!(
        (judge.calls, judge.rollouts),
        (7, 30),
        "one rollout per epoch"
    );
    assert_eq!((twin[29].network_epoch, twin[29].network_twin), (20, true));
    assert!(last.ends_with(",20,1"), "train.csv says whose: {last}");
    assert!(twin[29].kept().contains("model twin's epoch 20"));
    let (own, last, own_q, _) = run(&cfg, 5);
    assert_eq!((own[29].network_epoch, own[29].network_twin), (20, false));
    assert!(last.ends_with(",20,0"), "{last}");
    assert!(
        !twin_q.allclose(&own_q, 1e-6, 1e-6, false),
        "the twin's epoch 20 is another network"
    );

    // The twin leaves the run's own training as it was; without model rows there is none.
    cfg.learner.model_rows = 0;
    let (alone, _, alone_q, judge) = run(&cfg, 2);
    assert_eq!((judge.calls, judge.rollouts), (4, 0));
    assert_eq!(
        (alone[29].network_epoch, alone[29].network_twin),
        (20, false)
    );
    assert!(alone_q.allclose(&own_q, 0.0, 0.0, false));
    for (a, b) in alone.iter().zip(&own).take(29) {
        assert_eq!((a.td_loss, a.policy), (b.td_loss, b.policy));
    }
}
