//! Meta-training learns, measured in the true world: a `w0` meta-trained on five lambdas scores
//! far better zero-shot on the unseen lambda = 300 than the random init it started from, and
//! than the uniform random policy.
//!
//! The meta-train datasets come from a cheap behaviour policy (the stalest heuristic with 10%
//! random actions) rather than online DQN agents, so that the test takes seconds; what is
//! checked is MAML's part: the pass-per-meta-epoch budget of SPEC section 5 moves `w0` from
//! random to a policy of the data's quality.

use uavmeta_actors::collect::Collector;
use uavmeta_actors::policy::heuristics::{EpsilonPolicy, RandomPolicy};
use uavmeta_actors::policy::q_policy::Evaluator;
use uavmeta_actors::rollout::evaluate;
use uavmeta_learner::batch::Batch;
use uavmeta_learner::qnet::QNetworkConfig;
use uavmeta_learner::train::EvaluatePolicy;
use uavmeta_meta::maml::{Maml, MamlConfig, MetaTask};
use uavmeta_proto::config::Config;
use uavmeta_proto::dataset::split;

const DEFAULT_CONFIG: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/../configs/default.toml");
const EVAL_EPISODES: usize = 20;
const EVAL_SEED: u64 = 4242;

fn meta_task(config: &Config, name: &str, seed: u64) -> MetaTask {
    let task = config.task(name).unwrap();
    let mut data = Vec::new();
    Collector::new(
        &config.world,
        task,
        0,
        0,
        Box::new(EpsilonPolicy::new(0.1, seed)),
        seed,
    )
    .fill(config.collect.transitions, &mut data);
    let (support, query) = split(&data, config.meta.support_fraction, seed).unwrap();
    let encode = |set: &[_]| Batch::new(set, &config.world, config.learner.reward_scale).unwrap();
    MetaTask {
        name: name.to_string(),
        support: encode(&support),
        query: encode(&query),
    }
}

#[test]
fn a_meta_trained_w0_beats_a_random_init_zero_shot_on_an_unseen_lambda() {
    tch::set_num_threads(1);
    let config = Config::load(DEFAULT_CONFIG.as_ref(), &[]).unwrap();
    let tasks: Vec<MetaTask> = [
        "lambda-0",
        "lambda-200",
        "lambda-500",
        "lambda-800",
        "lambda-1000",
    ]
    .iter()
    .zip(1..)
    .map(|(name, seed)| meta_task(&config, name, seed))
    .collect();
    let w = &config.world;
    let init = QNetworkConfig::for_world(w, &config.learner.hidden).init(5);
    let unseen = config.task("lambda-300").unwrap();
    let mut evaluator = Evaluator::new(w, unseen, EVAL_EPISODES, EVAL_SEED);
    let before = evaluator.evaluate(&init);

    let mut maml = Maml::new(init, MamlConfig::from_config(&config), 6).unwrap();
    for _ in 0..config.meta.meta_epochs {
        maml.meta_epoch(&tasks).unwrap();
    }
    let after = evaluator.evaluate(maml.w0());
    let random = evaluate(
        w,
        unseen,
        &mut RandomPolicy::new(7),
        EVAL_EPISODES,
        EVAL_SEED,
    );
    eprintln!(
        "random init: return {:.1}, AoI {:.2}",
        before.ret, before.aoi
    );
    eprintln!(
        "meta-trained w0: return {:.1}, AoI {:.2}",
        after.ret, after.aoi
    );
    eprintln!(
        "random policy: return {:.1}, AoI {:.2}",
        random.ret, random.aoi
    );
    // Returns are costs: a wide margin is at least halving the random init's cost, and beating
    // the random policy by a fifth.
    assert!(
        after.ret.mean > 0.5 * before.ret.mean,
        "w0 {} vs init {}",
        after.ret,
        before.ret
    );
    assert!(
        after.ret.mean > 0.8 * random.ret.mean,
        "w0 {} vs random {}",
        after.ret,
        random.ret
    );
}
