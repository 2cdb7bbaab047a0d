//! Meta-test (`uavmeta meta-test`), docs/MODEL.md section 5: from a meta-learned `w0` checkpoint,
//! fine-tune on N shots of an unseen task for E epochs, evaluating the greedy policy after every
//! epoch.
//!
//! Fine-tuning is the learner's offline training ([`uavmeta_learner::train::train`]) started from
//! `w0` instead of a random init, so it has the same optimiser settings, target-network schedule
//! and `train.csv` columns as `uavmeta train`, which is what makes the methods comparable. The
//! algorithm follows the checkpoint: a `cql-maml` init is fine-tuned with CQL (eq. 8), a
//! `dqn-maml` init with DQN (eq. 7).

use std::path::Path;

use uavmeta_actors::policy::q_policy::Evaluator;
use uavmeta_learner::checkpoint;
use uavmeta_learner::progress::OnStep;
use uavmeta_learner::qnet::QNetwork;
use uavmeta_learner::train::{train, EpochRow, EvaluatePolicy, TrainOptions};
use uavmeta_learner::transitions::{load_shots, Transitions};
use uavmeta_proto::config::{Config, TaskConfig};
use uavmeta_proto::method::{Algo, Method, Start};
use uavmeta_proto::stats::PolicyMetrics;

use crate::context::ContextModel;
use crate::MetaError;

/// The settings of one fine-tuning run, shared by meta-test and the baselines it is compared to.
pub struct FineTune<'a> {
    /// `[learner]` drives fine-tuning; its `epochs` is replaced by `epochs`.
    pub config: &'a Config,
    /// The unseen task: its environment scores the policy after every epoch.
    pub task: &'a TaskConfig,
    pub epochs: usize,
    /// Seed of the minibatch order.
    pub seed: u64,
    /// Where `train.csv` and the `final` checkpoint go.
    pub out_dir: Option<&'a Path>,
    pub progress: bool,
    /// Called at every gradient step.
    pub on_step: OnStep,
}

impl FineTune<'_> {
    /// The config that trains: `config` with `learner.epochs` = `epochs`.
    fn training_config(&self) -> Config {
        let mut config = self.config.clone();
        config.learner.epochs = self.epochs;
        config
    }
}

/// One meta-test run.
pub struct MetaTestOptions<'a> {
    pub fine_tune: FineTune<'a>,
    /// The w0 checkpoint written by meta-train.
    pub init: &'a Path,
    /// The task's dataset file; `shots` transitions are drawn from it, seeded by `fine_tune.seed`.
    pub dataset: &'a Path,
    pub shots: usize,
}

/// The algorithm that fine-tunes an init written by meta-train, by multi-task pretraining or by
/// the context learner: that of the method its checkpoint names (`cql-maml`, `cql-pretrain`,
/// `cql-context`, ..).
pub fn fine_tune_algorithm(init: &Path, algorithm: &str) -> Result<Algo, MetaError> {
    Method::from_name(algorithm)
        .filter(|m| {
            matches!(
                m.start(),
                Some(Start::Maml | Start::Pretrain | Start::Context)
            )
        })
        .and_then(Method::algo)
        .ok_or_else(|| MetaError::NotMetaTrained {
            path: init.to_path_buf(),
            algorithm: algorithm.to_string(),
        })
}

/// Offline training of `q` on `shots` with the config's settings for `epochs` epochs, scored by
/// `evaluator` after every epoch: the common fine-tuning of every method of the paper's
/// comparison.
pub fn fine_tune(
    q: &mut QNetwork,
    shots: &Transitions,
    algorithm: Algo,
    run: &FineTune,
    evaluator: &mut dyn EvaluatePolicy,
) -> Result<Vec<EpochRow>, MetaError> {
    let config = run.training_config();
    let train_opts = TrainOptions {
        algorithm,
        config: &config,
        seed: run.seed,
        out_dir: run.out_dir,
        progress: run.progress,
        on_step: run.on_step.clone(),
    };
    Ok(train(q, shots, &train_opts, evaluator)?)
}

/// What a meta-test run scored: its init before any gradient step (the context learner's
/// zero-shot policy, w0's own) and one row per epoch.
pub struct MetaTestResult {
    pub init: PolicyMetrics,
    pub rows: Vec<EpochRow>,
}

/// Loads the init `opts.init` and fine-tunes it, scored on the task's true environment before
/// the first step and after every epoch (the rows also in `<out_dir>/train.csv`), keeping the
/// network that does best in the world the shots identify.
pub fn meta_test(opts: &MetaTestOptions) -> Result<MetaTestResult, MetaError> {
    let run = &opts.fine_tune;
    let shots = load_shots(run.config, run.task, opts.dataset, opts.shots, run.seed)?;
    let evaluator = &mut Evaluator::from_config(run.config, run.task).with_model(&shots.rows);
    let (mut q, algorithm) = init_network(opts.init, run.config, &shots.data)?;
    let init = evaluator.evaluate(&q);
    let rows = fine_tune(&mut q, &shots.data, algorithm, run, evaluator)?;
    Ok(MetaTestResult { init, rows })
}

/// The network meta-test starts from with the init `path`, and the algorithm that fine-tunes
/// it: w0 or a pretrained network as saved, or the context learner's policy for the task code
/// of `shots` (its zero-shot policy).
pub fn init_network(
    path: &Path,
    config: &Config,
    shots: &Transitions,
) -> Result<(QNetwork, Algo), MetaError> {
    let meta = checkpoint::read_meta(path)?;
    let algorithm = fine_tune_algorithm(path, &meta.algorithm)?;
    let q = match checkpoint::is_context_model(&meta, config) {
        true => ContextModel::load(path, config)?.policy(shots),
        false => checkpoint::load(path, config)?.0,
    };
    Ok((q, algorithm))
}
