//! Meta-training learns, measured in the true world: a `w0` meta-trained on five lambdas scores
//! far better zero-shot on the unseen lambda = 300 than the random init it started from, and
//! than the uniform random policy; and, with the default config's averaging and w0 loss, it
//! holds still (within 2%) over the last 30 meta-epochs.
//!
//! The meta-train datasets come from a cheap behaviour policy (the stalest heuristic with 10%
//! random actions) rather than online DQN agents, so that the test takes seconds; what is
//! checked is MAML's part: the pass-per-meta-epoch budget of docs/MODEL.md section 5 moves `w0`
//! from random to a policy of the data's quality.

mod support;

use support::meta_task;
use uavmeta_actors::policy::q_policy::Evaluator;
use uavmeta_learner::qnet::QNetworkConfig;
use uavmeta_learner::train::EvaluatePolicy;
use uavmeta_meta::maml::{Maml, MamlConfig, MetaTask};
use uavmeta_proto::config::Config;
use uavmeta_world::heuristics::RandomPolicy;
use uavmeta_world::rollout::evaluate;

const DEFAULT_CONFIG: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/../configs/default.toml");
const EVAL_EPISODES: usize = 20;
const EVAL_SEED: u64 = 4242;

/// configs/default.toml with 500 transitions per task, the size these tests were measured at:
/// with the default's 2 000 of this data (and `meta.alpha = 1`, the default then) w0 swung by
/// 2.55% over the last 30 meta-epochs (docs/EXPERIMENTS.md C14, C16), and the two tests took
/// 126 s instead of 50 s.
fn default_config() -> Config {
    let sets = ["collect.transitions=500".to_string()];
    Config::load(DEFAULT_CONFIG.as_ref(), &sets).unwrap()
}

/// Five of the default config's meta-train tasks.
fn meta_tasks(config: &Config) -> Vec<MetaTask> {
    [
        "lambda-0",
        "lambda-200",
        "lambda-500",
        "lambda-800",
        "lambda-1000",
    ]
    .iter()
    .zip(1..)
    .map(|(name, seed)| meta_task(config, name, seed))
    .collect()
}

#[test]
fn a_meta_trained_w0_beats_a_random_init_zero_shot_on_an_unseen_lambda() {
    tch::set_num_threads(1);
    let config = default_config();
    let tasks = meta_tasks(&config);
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

/// With configs/default.toml's averaging of the meta-iterates (`meta.average_decay_per_outer_step`) and w0's
/// own loss in the meta-loss (`meta.w0_loss_weight`), w0's zero-shot return on the unseen
/// lambda = 300, evaluated exactly over the 100 start cells after each of the last 30
/// meta-epochs, varies by less than issue #30's 2% (max - min over mean). Measured here on an
/// Intel Xeon: 1.5% with both; 2.5% with the averaging alone and 7.4% with neither, so the test
/// fails without either (docs/EXPERIMENTS.md, C7 and C10).
#[test]
fn w0_zero_shot_varies_by_under_2_percent_over_the_last_30_meta_epochs() {
    tch::set_num_threads(1);
    let config = default_config();
    assert!(
        config.meta.average_decay_per_outer_step > 0.0 && config.meta.w0_loss_weight > 0.0,
        "the default config averages w0 and adds its own loss to the meta-loss"
    );
    let tasks = meta_tasks(&config);
    let w = &config.world;
    let init = QNetworkConfig::for_world(w, &config.learner.hidden).init(5);
    let mut evaluator = Evaluator::new(w, config.task("lambda-300").unwrap(), 1, EVAL_SEED);
    let mut maml = Maml::new(init, MamlConfig::from_config(&config), 6).unwrap();
    let epochs = config.meta.meta_epochs;
    let mut returns = Vec::new();
    for epoch in 0..epochs {
        maml.meta_epoch(&tasks).unwrap();
        if epoch + 30 >= epochs {
            let m = evaluator.evaluate(maml.w0());
            assert_eq!(m.episodes, 100, "exact: one episode per start cell");
            returns.push(m.ret.mean);
        }
    }
    let mean = returns.iter().sum::<f64>() / returns.len() as f64;
    let (lo, hi) = returns
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), &r| {
            (lo.min(r), hi.max(r))
        });
    let swing = (hi - lo) / mean.abs();
    eprintln!(
        "w0 over the last 30 meta-epochs: {lo:.1} to {hi:.1}, swing {:.2}%",
        100.0 * swing
    );
    assert!(
        swing < 0.02,
        "w0 swings by {:.2}% over the last 30 meta-epochs ({lo:.1} to {hi:.1})",
        100.0 * swing
    );
}
