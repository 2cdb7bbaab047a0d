//! Offline training end to end on a synthetic contextual bandit the test can score exactly:
//! K = 1 (obs [x, y, A], 5 actions), the rewarded action is 1 when x < 5 and 3 otherwise.

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use tch::Tensor;
use uavmeta_learner::batch::Batch;
use uavmeta_learner::checkpoint;
use uavmeta_learner::progress::OnStep;
use uavmeta_learner::qnet::{QNetwork, QNetworkConfig};
use uavmeta_learner::train::{train, EvaluatePolicy, TrainOptions};
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
    let mut rng = ChaCha8Rng::seed_from_u64(1);
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
