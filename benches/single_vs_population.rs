//! Issue #59's measurement: does a population of one run at the single learner's speed?
//!
//! Each pair runs the same work through the single implementation and through the population
//! layer with one member, interleaved, five rounds; it prints each round's seconds per unit and
//! the medians. Work: offline CQL (`train` against `train_population`, 500 shots, 20 epochs, no
//! evaluation), the online DQN agent (`OnlineDqn` against `DqnPopulation`, 2 000 environment steps
//! after a 200-step warm-up) and MAML (`Maml::meta_epoch` against `MamlPopulation::meta_epoch`,
//! eight tasks of 250 support and 250 query shots). Default config otherwise (hidden [256, 256],
//! K = 10), one libtorch thread.
//!
//! Run: `cargo bench --bench single_vs_population`.

use std::time::Instant;

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use tch::{Device, Tensor};
use uavmeta_actors::policy::dqn_online::OnlineDqn;
use uavmeta_actors::policy::dqn_population::{DqnPopulation, MemberSpec};
use uavmeta_learner::batch::Batch;
use uavmeta_learner::progress::OnStep;
use uavmeta_learner::qnet::{QNetwork, QNetworkConfig};
use uavmeta_learner::train::{train, EvaluatePolicy, TrainOptions};
use uavmeta_learner::train_population::{train_population, Member, PopulationOptions};
use uavmeta_meta::maml::{Maml, MamlConfig, MetaTask};
use uavmeta_meta::maml_population::MamlPopulation;
use uavmeta_proto::config::{Config, Loss};
use uavmeta_proto::stats::PolicyMetrics;

struct NoEvaluation;

impl EvaluatePolicy for NoEvaluation {
    fn evaluate(&mut self, _q: &QNetwork) -> PolicyMetrics {
        PolicyMetrics::default()
    }
}

fn random_batch(config: &Config, rows: usize, rng: &mut ChaCha8Rng) -> Batch {
    let d = config.world.observation_len();
    let a = config.world.action_count() as i64;
    let mut uniform = |n: usize| -> Vec<f32> { (0..n).map(|_| rng.random_range(0.0..1.0)).collect() };
    let obs = uniform(rows * d);
    let next_obs = uniform(rows * d);
    let rewards: Vec<f32> = uniform(rows).iter().map(|u| -u).collect();
    let actions: Vec<i64> = uniform(rows).iter().map(|u| (*u * a as f32) as i64 % a).collect();
    Batch {
        obs: Tensor::from_slice(&obs).view([rows as i64, d as i64]),
        actions: Tensor::from_slice(&actions),
        rewards: Tensor::from_slice(&rewards),
        next_obs: Tensor::from_slice(&next_obs).view([rows as i64, d as i64]),
    }
}

fn seconds(f: impl FnOnce()) -> f64 {
    let start = Instant::now();
    f();
    start.elapsed().as_secs_f64()
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

fn report(name: &str, unit: &str, single: Vec<f64>, population: Vec<f64>) {
    let fmt = |v: &[f64]| v.iter().map(|s| format!("{:.3}", s * 1e3)).collect::<Vec<_>>().join(", ");
    let (s, p) = (median(single.clone()), median(population.clone()));
    println!(
        "| {name} | ms per {unit} | {} | {} | {:.3} | {:.3} | {:.3} |",
        fmt(&single),
        fmt(&population),
        s * 1e3,
        p * 1e3,
        p / s
    );
}

fn main() {
    tch::set_num_threads(1);
    const ROUNDS: usize = 5;
    let mut rng = ChaCha8Rng::seed_from_u64(0);
    println!("| work | unit | single (rounds) | population of one (rounds) | single median | population median | population / single |");
    println!("| --- | --- | --- | --- | ---: | ---: | ---: |");

    // Offline CQL: 500 shots, 20 epochs of 8 steps.
    let config = Config::from_toml_str("", "bench", &["learner.epochs=20".into()]).unwrap();
    let data = random_batch(&config, 500, &mut rng);
    let net = QNetworkConfig::for_world(&config.world, &config.learner.hidden);
    let steps = (20 * 500usize.div_ceil(64)) as f64;
    let (mut single, mut population) = (Vec::new(), Vec::new());
    for _ in 0..ROUNDS {
        single.push(seconds(|| {
            let mut q = net.init(1);
            let opts = TrainOptions {
                algorithm: Loss::Cql,
                config: &config,
                seed: 2,
                out_dir: None,
                progress: false,
                on_step: OnStep::default(),
            };
            train(&mut q, &data, &opts, &mut NoEvaluation).unwrap();
        }) / steps);
        population.push(seconds(|| {
            let mut eval = NoEvaluation;
            let member = Member { init: net.init(1), data: &data, seed: 2, evaluator: &mut eval, out_dir: None };
            let opts = PopulationOptions { algorithm: Loss::Cql, config: &config, device: Device::Cpu, on_step: OnStep::default() };
            train_population(vec![member], &opts).unwrap();
        }) / steps);
    }
    report("offline CQL (`train`)", "gradient step", single, population);

    // Online DQN: 200 warm-up steps, then 2 000 steps with a gradient step each.
    let config = Config::from_toml_str(
        "",
        "bench",
        &["collect.learning_starts=200".into(), "collect.dqn_steps=2200".into()],
    )
    .unwrap();
    let task = config.tasks[0].clone();
    let (mut single, mut population) = (Vec::new(), Vec::new());
    for _ in 0..ROUNDS {
        let mut agent = OnlineDqn::new(&config, &task, 0, 0, 3);
        agent.train_steps(200).unwrap();
        single.push(seconds(|| agent.train_steps(2000).unwrap()) / 2000.0);
        let spec = MemberSpec { task: task.clone(), task_id: 0, actor: 0, seed: 3 };
        let mut agents = DqnPopulation::new(&config, &[spec], Device::Cpu);
        agents.train_steps(200).unwrap();
        population.push(seconds(|| agents.train_steps(2000).unwrap()) / 2000.0);
    }
    report("online DQN agent", "environment step", single, population);

    // MAML: eight tasks of 250 + 250 shots, one meta-epoch (4 outer steps at k = 64).
    let config = Config::default();
    let tasks: Vec<MetaTask> = (0..8)
        .map(|i| MetaTask {
            name: format!("t{i}"),
            support: random_batch(&config, 250, &mut rng),
            query: random_batch(&config, 250, &mut rng),
        })
        .collect();
    let net = QNetworkConfig::for_world(&config.world, &config.learner.hidden);
    let settings = MamlConfig::from_config(&config);
    let (mut single, mut population) = (Vec::new(), Vec::new());
    for _ in 0..ROUNDS {
        let mut maml = Maml::new(net.init(4), settings.clone(), 5).unwrap();
        maml.meta_epoch(&tasks).unwrap();
        single.push(seconds(|| {
            for _ in 0..3 {
                maml.meta_epoch(&tasks).unwrap();
            }
        }) / 3.0);
        let mut pop = MamlPopulation::new(&[net.init(4)], settings.clone(), &[5], Device::Cpu);
        pop.meta_epoch(&[&tasks]).unwrap();
        population.push(seconds(|| {
            for _ in 0..3 {
                pop.meta_epoch(&[&tasks]).unwrap();
            }
        }) / 3.0);
    }
    report("MAML (`meta_epoch`)", "meta-epoch", single, population);
}
