//! The learners learn, measured in the true world:
//! - online DQN on configs/default.toml reaches the heuristics' level, and on a small world comes
//!   within 8% of the planner (mean of three seeds);
//! - CQL on 500 shots of that agent's replay buffer comes within 10% of the agent;
//! - CQL on a dataset of the "stalest" heuristic recovers a greedy policy within 10% of that
//!   heuristic's return;
//! - offline DQN on the same dataset overestimates (mean Q far above its measured return) while
//!   CQL's mean Q stays near its own return.

use std::sync::OnceLock;

use uavmeta_actors::collect::{online_dqn_dataset, Collector};
use uavmeta_actors::policy::dqn_online::OnlineDqn;
use uavmeta_actors::policy::q_policy::Evaluator;
use uavmeta_learner::progress::OnStep;
use uavmeta_learner::qnet::{QNetwork, QNetworkConfig};
use uavmeta_learner::train::{train, EpochRow, EvaluatePolicy, TrainOptions};
use uavmeta_learner::transitions::Transitions;
use uavmeta_proto::config::Config;
use uavmeta_proto::dataset::Transition;
use uavmeta_proto::method::Algo;
use uavmeta_proto::stats::PolicyMetrics;
use uavmeta_world::heuristics::{GreedyPolicy, PolicySpec, RandomPolicy, StalestPolicy};
use uavmeta_world::rollout::{evaluate, Policy};

mod support;
use support::DEFAULT_CONFIG;
const EVAL_EPISODES: usize = 30;
const EVAL_SEED: u64 = 777;

/// One libtorch thread: these networks are far too small to gain from intra-op parallelism, and on
/// a shared two-core machine OpenMP workers spin-waiting for a busy core made the online DQN test
/// 25x slower (145 s against 6 s, the same figures).
fn single_threaded() {
    tch::set_num_threads(1);
}

/// What the online DQN agent of configs/default.toml on lambda-300 leaves behind, made through
/// the collection path (`online_dqn_dataset`): its greedy policy's figures and the 500
/// transitions sampled from its replay buffer.
struct TrainedAgent {
    policy: PolicyMetrics,
    dataset: Vec<Transition>,
}

fn trained_agent() -> TrainedAgent {
    single_threaded();
    // Half of configs/default.toml's 120 000 steps, and a quarter of its 2 000 transitions
    // (the fine-tuning's 500 shots), to keep the suite quick: these tests check that the
    // learners learn, not how close to the planner they come.
    let overrides = [
        "collect.dqn.steps=60000".into(),
        "collect.transitions=500".into(),
    ];
    let config = Config::load(DEFAULT_CONFIG.as_ref(), &overrides).unwrap();
    let task = config.task("lambda-300").unwrap().clone();
    let (dataset, agent) = online_dqn_dataset(&config, &task, 0, 0, 1, |_, _| true).unwrap();
    assert_eq!(agent.steps(), config.collect.dqn.steps);
    assert_eq!(dataset.len(), config.collect.transitions);
    let policy =
        Evaluator::new(&config.world, &task, EVAL_EPISODES, EVAL_SEED).evaluate(agent.q_network());
    TrainedAgent { policy, dataset }
}

/// A fixed policy on lambda-300 over the tests' evaluation episodes.
fn heuristic(config: &Config, policy: &mut dyn Policy) -> PolicyMetrics {
    let task = config.task("lambda-300").unwrap();
    evaluate(&config.world, task, policy, EVAL_EPISODES, EVAL_SEED)
}

/// One test for the two claims on the one agent: the make test runner (cargo-nextest) runs each
/// test in its own process, so two tests would train it twice (a minute each).
#[test]
fn online_dqn_reaches_the_heuristics_and_cql_on_500_shots_of_its_replay_comes_within_10_percent() {
    let agent = trained_agent();
    online_dqn_reaches_the_heuristics_on_the_default_config(&agent);
    cql_on_500_shots_of_the_agents_replay_comes_within_10_percent_of_the_agent(&agent);
}

fn online_dqn_reaches_the_heuristics_on_the_default_config(agent: &TrainedAgent) {
    let config = Config::load(DEFAULT_CONFIG.as_ref(), &[]).unwrap();
    let dqn = &agent.policy;
    let random = heuristic(&config, &mut RandomPolicy::new(3));
    let stalest = heuristic(&config, &mut StalestPolicy);
    let greedy = heuristic(&config, &mut GreedyPolicy);
    for (name, m) in [
        ("online DQN", dqn),
        ("random", &random),
        ("stalest", &stalest),
        ("greedy", &greedy),
    ] {
        eprintln!(
            "{name:>10}: return {:.1}, AoI {:.2}, power {:.3} mW",
            m.ret, m.aoi, m.power_mw
        );
    }
    // The bar: at least the worse heuristic; and far from random (returns are costs).
    let worse = stalest.ret.mean.min(greedy.ret.mean);
    assert!(
        dqn.ret.mean >= worse,
        "online DQN {} < worse heuristic {worse}",
        dqn.ret.mean
    );
    assert!(
        dqn.ret.mean > 0.8 * random.ret.mean,
        "online DQN {} is not clearly above random {}",
        dqn.ret.mean,
        random.ret.mean
    );
}

/// On a world small enough for the planner to be the optimum (4 x 4 cells, 3 devices, 20 steps:
/// world/tests/planner.rs checks the default search against one 256 times wider there), online
/// DQN comes within 8% of it on the mean of three seeds and within 15% on each, evaluated exactly
/// over the 16 start cells, where the greedy heuristic is 62% short. It keeps its best snapshot
/// as configs/default.toml does (`collect.dqn.select_every`). (Before selection, eight seeds at
/// this budget ended 1.6-12.4% short, 4.9% on average.)
#[test]
fn online_dqn_comes_within_8_percent_of_the_planner_on_a_small_world() {
    single_threaded();
    let config = small_world(&[]);
    let task = uavmeta_proto::config::TaskConfig::one_off(300.0, None);
    let exact = |policy: &mut dyn Policy| evaluate(&config.world, &task, policy, 1, 0).ret.mean;
    let planner = exact(
        PolicySpec::Planner
            .build(&config, 0, None)
            .unwrap()
            .as_mut(),
    );
    let greedy = exact(&mut GreedyPolicy);
    let seeds = 0..3;
    let returns: Vec<f64> = seeds
        .clone()
        .map(|seed| {
            let mut agent = OnlineDqn::new(&config, &task, 0, 0, seed);
            agent.train().unwrap();
            let dqn = Evaluator::new(&config.world, &task, 1, 0).evaluate(agent.q_network());
            assert_eq!(dqn.episodes, 16, "one episode per start cell");
            eprintln!(
                "seed {seed}: online DQN {:.1}, planner {planner:.1}, greedy {greedy:.1}",
                dqn.ret.mean
            );
            dqn.ret.mean
        })
        .collect();
    let mean = returns.iter().sum::<f64>() / returns.len() as f64;
    assert!(
        mean >= 1.08 * planner,
        "online DQN's mean {mean:.1} over seeds {seeds:?} is more than 8% short of the planner's {planner:.1}"
    );
    for (seed, ret) in seeds.zip(&returns) {
        assert!(
            *ret >= 1.15 * planner,
            "seed {seed}: online DQN {ret:.1} is more than 15% short of the planner's {planner:.1}"
        );
    }
}

/// configs/default.toml on the small world of the planner's tests (4 x 4 cells, 3 devices, 20
/// steps) with an 8 000-step online agent, and `extra` settings.
fn small_world(extra: &[&str]) -> Config {
    let agent = [
        "collect.dqn.steps=8000",
        "collect.dqn.replay_capacity=8000",
        "collect.dqn.eps_decay_steps=3000",
        "collect.dqn.learning_starts=500",
        "collect.dqn.target_update_every=500",
    ];
    support::small_world(&[&agent[..], extra].concat())
}

/// Snapshot selection (`collect.dqn.select_every`) keeps the best of the greedy policies it
/// evaluates and touches nothing else: with and without it the same seed fills the same replay
/// buffer, and the kept policy is the best of the candidates (every 1 000 steps once epsilon is
/// at its floor, and the last), each scored here exactly over the 16 start cells.
#[test]
fn snapshot_selection_keeps_the_best_candidate_and_leaves_training_alone() {
    single_threaded();
    let off = small_world(&["collect.dqn.select_every=0", "collect.dqn.steps=6000"]);
    let on = small_world(&["collect.dqn.select_every=1000", "collect.dqn.steps=6000"]);
    let task = uavmeta_proto::config::TaskConfig::one_off(300.0, None);
    let exact = Evaluator::new(&off.world, &task, 1, 0);
    let mut plain = OnlineDqn::new(&off, &task, 0, 0, 5);
    let mut candidates = vec![];
    while plain.steps() < off.collect.dqn.steps {
        plain.train_steps(1000).unwrap();
        if plain.steps() >= 3500 {
            candidates.push((
                plain.steps(),
                exact.clone().evaluate(plain.q_network()).ret.mean,
            ));
        }
    }
    let mut selecting = OnlineDqn::new(&on, &task, 0, 0, 5);
    selecting.train().unwrap();

    let buffer = |a: &OnlineDqn| a.replay_buffer().iter().cloned().collect::<Vec<_>>();
    assert!(
        buffer(&plain) == buffer(&selecting),
        "selection changed the replay buffer"
    );
    assert_eq!(plain.episode_returns(), selecting.episode_returns());
    let best = candidates
        .iter()
        .copied()
        .reduce(|b, c| if c.1 > b.1 { c } else { b })
        .unwrap();
    eprintln!(
        "candidates (step, return): {candidates:?}; kept {:?}",
        selecting.selected()
    );
    assert_eq!(selecting.selected(), Some(best));
    let kept = exact.clone().evaluate(selecting.q_network()).ret.mean;
    assert_eq!(
        kept, best.1,
        "the kept network does not score its recorded return"
    );
    let last = candidates.last().unwrap().1;
    assert!(kept >= last, "kept {kept} below the last policy's {last}");
}

fn cql_on_500_shots_of_the_agents_replay_comes_within_10_percent_of_the_agent(
    agent: &TrainedAgent,
) {
    // The default 100 one-pass epochs of 8 steps, as `make run` trains: on the shots of the 60
    // 000-step agents CQL has converged by then (make run's three seeds end 1.7-3.1% below their
    // agents). The 250 epochs this test took with the 15 000-step agents' shots end 10.5% below
    // here: CQL declines after it has converged (docs/EXPERIMENTS.md, D).
    let config =
        Config::load(DEFAULT_CONFIG.as_ref(), &["learner.eval_episodes=5".into()]).unwrap();
    let (q, _) = train_offline(&config, &agent.dataset, Algo::CQL);
    let task = config.task("lambda-300").unwrap();
    let cql = Evaluator::new(&config.world, task, EVAL_EPISODES, EVAL_SEED).evaluate(&q);
    eprintln!(
        "CQL:        return {:.1}, AoI {:.2}, power {:.3} mW",
        cql.ret, cql.aoi, cql.power_mw
    );
    eprintln!("online DQN: return {:.1}", agent.policy.ret);
    let gap = (agent.policy.ret.mean - cql.ret.mean) / agent.policy.ret.mean.abs();
    assert!(
        gap <= 0.10,
        "CQL is {:.1}% below the agent whose replay it learned from",
        100.0 * gap
    );
}

/// The default world with a learner small enough that each offline run takes seconds: 4000
/// gradient steps, and a target network synced every 10 steps so that values propagate over
/// gamma = 0.99's horizon of about 100 steps within that budget.
fn offline_config() -> Config {
    let overrides = [
        "learner.hidden=[64, 64]".to_string(),
        "learner.epochs=40".into(),
        "learner.steps_per_epoch=100".into(),
        "learner.target_update_every=10".into(),
        "learner.batch_size=128".into(),
        "learner.eval_episodes=10".into(),
    ];
    Config::load(DEFAULT_CONFIG.as_ref(), &overrides).unwrap()
}

fn stalest_dataset(config: &Config, transitions: usize) -> Vec<Transition> {
    let task = config.task("lambda-300").unwrap();
    let mut out = Vec::new();
    Collector::new(&config.world, task, 0, 0, Box::new(StalestPolicy), 5)
        .fill(transitions, &mut out);
    out
}

fn train_offline(
    config: &Config,
    data: &[Transition],
    algorithm: Algo,
) -> (QNetwork, Vec<EpochRow>) {
    let task = config.task("lambda-300").unwrap();
    let batch = Transitions::new(data, &config.world, config.learner.reward_scale).unwrap();
    let mut q = QNetworkConfig::for_world(&config.world, &config.learner.hidden).init(11);
    let opts = TrainOptions {
        algorithm,
        config,
        seed: 2,
        out_dir: None,
        progress: false,
        on_step: OnStep::default(),
    };
    let rows = train(
        &mut q,
        &batch,
        &opts,
        &mut Evaluator::from_config(config, task),
    )
    .unwrap();
    (q, rows)
}

/// CQL on the stalest dataset, shared by the two tests that need it when they run in one process
/// (`cargo test`); under cargo-nextest each test trains it itself, a few seconds each.
struct CqlRun {
    policy: PolicyMetrics,
    mean_q: f64,
}

fn cql_on_stalest() -> &'static CqlRun {
    static RUN: OnceLock<CqlRun> = OnceLock::new();
    RUN.get_or_init(|| {
        let config = offline_config();
        let task = config.task("lambda-300").unwrap();
        let (q, rows) = train_offline(&config, &stalest_dataset(&config, 2000), Algo::CQL);
        let policy = Evaluator::new(&config.world, task, EVAL_EPISODES, EVAL_SEED).evaluate(&q);
        CqlRun {
            policy,
            mean_q: rows.last().unwrap().mean_q,
        }
    })
}

#[test]
fn cql_recovers_the_stalest_heuristic() {
    single_threaded();
    let config = offline_config();
    let task = config.task("lambda-300").unwrap();
    let cql = cql_on_stalest();
    let stalest = evaluate(
        &config.world,
        task,
        &mut StalestPolicy,
        EVAL_EPISODES,
        EVAL_SEED,
    );
    let p = &cql.policy;
    eprintln!(
        "CQL:     return {:.1}, AoI {:.2}, power {:.3} mW, mean Q {:.1}",
        p.ret, p.aoi, p.power_mw, cql.mean_q
    );
    eprintln!(
        "stalest: return {:.1}, AoI {:.2}, power {:.3} mW",
        stalest.ret, stalest.aoi, stalest.power_mw
    );
    let gap = (p.ret.mean - stalest.ret.mean).abs() / stalest.ret.mean.abs();
    assert!(
        gap <= 0.10,
        "CQL's return is {:.1}% away from the heuristic's",
        100.0 * gap
    );
}

#[test]
fn offline_dqn_overestimates_and_cql_does_not() {
    single_threaded();
    let config = offline_config();
    let task = config.task("lambda-300").unwrap();
    let (dqn_q, dqn_rows) = train_offline(&config, &stalest_dataset(&config, 2000), Algo::DQN);
    let dqn_ret = Evaluator::new(&config.world, task, EVAL_EPISODES, EVAL_SEED)
        .evaluate(&dqn_q)
        .ret
        .mean;
    let dqn_mean_q = dqn_rows.last().unwrap().mean_q;
    let cql = cql_on_stalest();
    let (cql_ret, cql_mean_q) = (cql.policy.ret.mean, cql.mean_q);
    eprintln!("offline DQN: mean Q {dqn_mean_q:.1}, measured return {dqn_ret:.1}");
    eprintln!("CQL:         mean Q {cql_mean_q:.1}, measured return {cql_ret:.1}");
    // Returns are negative costs; "far above" = the believed value exceeds the achieved one by
    // more than half the return's size. CQL's belief stays within a quarter of its return.
    assert!(
        dqn_mean_q - dqn_ret > 0.5 * dqn_ret.abs(),
        "DQN does not overestimate"
    );
    assert!(
        (cql_mean_q - cql_ret).abs() < 0.25 * cql_ret.abs(),
        "CQL's mean Q is off its return"
    );
}
