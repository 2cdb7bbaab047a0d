//! Meta-training populations (issue #33): a population of one is `Maml` bit for bit, an unstacked
//! member continues exactly as its single meta-learner, and every member of a larger population
//! follows its own separate meta-training up to float rounding.

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use tch::{Device, Kind, Tensor};
use uavmeta_learner::batch::Batch;
use uavmeta_learner::dqn::TdConfig;
use uavmeta_learner::qnet::{QNetwork, QNetworkConfig};
use uavmeta_meta::maml::{Maml, MamlConfig, MetaTask};
use uavmeta_meta::maml_population::MamlPopulation;
use uavmeta_meta::MetaError;
use uavmeta_proto::config::{Loss, MetaConfig};

const OBS: usize = 3;
const ACTIONS: usize = 5;
const HIDDEN: [usize; 1] = [16];

/// Second-order CQL-MAML with everything that carries state across meta-epochs switched on in
/// turn: the target refresh (every 3), task sampling (2 of 3 tasks), Meta-SGD, averaging.
fn config(learn_inner_lr: bool, average: f64) -> MamlConfig {
    MamlConfig {
        meta: MetaConfig {
            inner_loss: Loss::Cql,
            alpha: 1.0,
            tasks_per_meta_epoch: 2,
            shots: 16,
            query_shots: 16,
            inner_steps: 2,
            eta_inner: 0.05,
            eta_outer: 3e-3,
            eta_outer_final_fraction: 0.5,
            meta_epochs: 8,
            first_order: false,
            learn_inner_lr,
            target_update_every: 3,
            outer_steps_per_meta_epoch: 0,
            w0_average_decay: average,
            ..MetaConfig::default()
        },
        td: TdConfig::eq7(0.9),
    }
}

/// `rows` random transitions of a task whose reward weighs the observation by `lambda`.
fn batch(rows: usize, lambda: f64, rng: &mut ChaCha8Rng) -> Batch {
    let mut uniform =
        |n: usize| -> Vec<f32> { (0..n).map(|_| rng.random_range(0.0..1.0)).collect() };
    let (obs, next_obs) = (uniform(rows * OBS), uniform(rows * OBS));
    let actions: Vec<i64> = (uniform(rows).iter())
        .map(|u| (u * ACTIONS as f32) as i64)
        .collect();
    let rewards: Vec<f32> = (0..rows)
        .map(|i| -(obs[i * OBS] + lambda as f32 * obs[i * OBS + 1]))
        .collect();
    let shape = [rows as i64, OBS as i64];
    Batch {
        obs: Tensor::from_slice(&obs).view(shape),
        actions: Tensor::from_slice(&actions),
        rewards: Tensor::from_slice(&rewards),
        next_obs: Tensor::from_slice(&next_obs).view(shape),
    }
}

/// A member's three tasks (40 support rows each: three outer steps of 16 shots per meta-epoch),
/// its own data drawn from `seed`.
fn tasks(seed: u64) -> Vec<MetaTask> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    (0..3)
        .map(|i| MetaTask {
            name: format!("task-{i}"),
            support: batch(40, i as f64, &mut rng),
            query: batch(24, i as f64, &mut rng),
        })
        .collect()
}

fn network(seed: u64) -> QNetwork {
    QNetworkConfig::new(OBS, ACTIONS, &HIDDEN).init(seed)
}

/// w0's weights, exactly (f32 widens to f64 without rounding).
fn weights(maml: &Maml) -> Vec<f64> {
    (maml.w0().parameters().iter())
        .flat_map(|p| Vec::<f64>::try_from(p.to_kind(Kind::Double).flatten(0, -1)).unwrap())
        .collect()
}

#[test]
fn a_population_of_one_is_the_single_meta_learner_bit_for_bit() {
    tch::set_num_threads(1);
    let data = tasks(5);
    for (learn_inner_lr, average) in [(false, 0.0), (true, 0.0), (false, 0.9)] {
        let c = config(learn_inner_lr, average);
        let (seed, epochs, unstacked_at) = (7, 8, 5);
        let mut single = Maml::new(network(3), c.clone(), seed).unwrap();
        let mut population = MamlPopulation::new(&[network(3)], c.clone(), &[seed], Device::Cpu);
        let mut single_rows = Vec::new();
        let mut population_rows = Vec::new();
        for _ in 0..unstacked_at {
            single_rows.push(single.meta_epoch(&data).unwrap());
            population_rows.extend(population.meta_epoch(&[&data]).unwrap());
        }
        let case = format!("learn_inner_lr {learn_inner_lr}, average {average}");
        assert_eq!(population_rows, single_rows, "{case}");
        let mut member = population.member(0);
        assert_eq!(weights(&member), weights(&single), "{case}");
        // The unstacked member carries the whole state (moments, target, step sizes, average,
        // sampling stream): it continues exactly as the single meta-learner does.
        for _ in unstacked_at..epochs {
            assert_eq!(
                member.meta_epoch(&data).unwrap(),
                single.meta_epoch(&data).unwrap(),
                "{case}"
            );
        }
        assert_eq!(weights(&member), weights(&single), "{case}");
        // Another seed samples other shots: the comparisons above can fail.
        let mut other = Maml::new(network(3), c, seed + 1).unwrap();
        for _ in 0..epochs {
            other.meta_epoch(&data).unwrap();
        }
        assert_ne!(weights(&other), weights(&single), "{case}");
    }
}

#[test]
fn each_member_follows_its_own_meta_training_up_to_rounding() {
    tch::set_num_threads(1);
    let seeds = [11u64, 12, 13];
    let data: Vec<Vec<MetaTask>> = seeds.iter().map(|&s| tasks(100 + s)).collect();
    let sets: Vec<&[MetaTask]> = data.iter().map(Vec::as_slice).collect();
    // The last case adds w0's own loss to eq. 15 (`meta.w0_loss_weight`), on the members' slots.
    for (learn_inner_lr, beta) in [(false, 0.0), (true, 0.0), (false, 0.5)] {
        let mut c = config(learn_inner_lr, 0.9);
        c.meta.w0_loss_weight = beta;
        let inits: Vec<QNetwork> = seeds.iter().map(|&s| network(s)).collect();
        let mut population = MamlPopulation::new(&inits, c.clone(), &seeds, Device::Cpu);
        let mut rows = vec![Vec::new(); seeds.len()];
        for _ in 0..6 {
            for (m, row) in population
                .meta_epoch(&sets)
                .unwrap()
                .into_iter()
                .enumerate()
            {
                rows[m].push(row);
            }
        }
        for (m, &seed) in seeds.iter().enumerate() {
            let mut alone = Maml::new(network(seed), c.clone(), seed).unwrap();
            let alone_rows: Vec<_> = (0..6)
                .map(|_| alone.meta_epoch(&data[m]).unwrap())
                .collect();
            let (a, b) = (weights(&alone), weights(&population.member(m)));
            let largest = a.iter().fold(0.0f64, |x, y| x.max(y.abs()));
            let off = a
                .iter()
                .zip(&b)
                .fold(0.0f64, |x, (a, b)| x.max((a - b).abs()));
            assert!(
                off <= 1e-4 * largest,
                "member {m} (learn_inner_lr {learn_inner_lr}, beta {beta}): {off} from its run alone"
            );
            for (alone, together) in alone_rows.iter().zip(&rows[m]) {
                let tasks = |r: &uavmeta_meta::maml::MetaEpoch| {
                    r.task_losses.iter().map(|&(t, _)| t).collect::<Vec<_>>()
                };
                // The same draws (tasks sampled), and losses equal up to rounding.
                assert_eq!(tasks(alone), tasks(together), "member {m}");
                let gap = (alone.meta_loss - together.meta_loss).abs();
                assert!(gap <= 1e-4 * alone.meta_loss.abs(), "member {m}: {gap}");
            }
            // Members never share: another member's run is far from this one.
            let other = weights(&population.member((m + 1) % seeds.len()));
            let apart = a
                .iter()
                .zip(&other)
                .fold(0.0f64, |x, (a, b)| x.max((a - b).abs()));
            assert!(apart > 1e3 * off.max(1e-7), "member {m}: {apart}");
        }
    }
}

#[test]
fn members_of_another_shape_are_refused_by_member() {
    let c = config(false, 0.0);
    let seeds = [1u64, 2];
    let inits: Vec<QNetwork> = seeds.iter().map(|&s| network(s)).collect();
    let mut population = MamlPopulation::new(&inits, c, &seeds, Device::Cpu);
    let full = tasks(1);
    let fewer = tasks(2).into_iter().take(2).collect::<Vec<_>>();
    let error = population.meta_epoch(&[&full, &fewer]).unwrap_err();
    assert!(
        matches!(error, MetaError::PopulationShape { member: 1, .. }),
        "{error}"
    );
    let text = error.to_string();
    assert!(
        text.contains("member 1") && text.contains("2 tasks") && text.contains("3 tasks"),
        "{text}"
    );
    let error = population.meta_epoch(&[&full]).unwrap_err().to_string();
    assert!(error.contains("one task set per member (2)"), "{error}");
}
