//! The meta-learner process (`uavmeta meta-learner --run R`): MAML over the run's datasets as
//! soon as the store announces them, then meta-test on the unseen task(s). It runs the library's
//! meta-training and fine-tuning (`meta_train_with`, `fine_tune`) with hooks that write into
//! the run directory and announce what they wrote.
//!
//! 1. Waits until the store has announced the dataset of every task (meta-train tasks for MAML,
//!    meta-test tasks for their few shots), then announces each meta-test task's online DQN
//!    agent (saved by its actor), the reference line.
//! 2. Meta-trains w0 (Algorithm 4) for `meta.meta_epochs` meta-epochs; every
//!    `meta.checkpoint_every` meta-epochs (and after the last) it writes w0 as a checkpoint
//!    (`uavmeta_learner::checkpoint`: write, fsync, rename) and announces it once per meta-test
//!    task, whose evaluator then scores it zero-shot. `meta-train/meta_train.csv` in the run
//!    directory holds the per-meta-epoch figures, as `uavmeta meta-train` writes them.
//! 3. Meta-tests: per meta-test task, fine-tunes w0 on `learner.shots` shots with the loss
//!    its checkpoint names (CQL-MAML or, with `meta.inner_loss = "dqn"`, DQN-MAML) and, as
//!    baselines, the same loss from a random init (CQL or DQN), from a network pretrained on
//!    the union of the meta-train tasks' shots (CQL-pretrain, `uavmeta_meta::pretrain`) and
//!    from the context learner's policy for the task's shots (CQL-context,
//!    `uavmeta_meta::context`), each for `learner.epochs` epochs, checkpointing and announcing
//!    every epoch. The context learner's policy before any step is announced too, as
//!    `context-init` epoch 1: its zero-shot row.
//!
//! The inits of the run are also saved where a user looks for them, to fine-tune on another
//! task afterwards: `inits/w0` (the final meta-learned init), `inits/cql-pretrain` and
//! `inits/cql-context` (the context learner's model, for `uavmeta meta-test --init`).
//!
//! **Restart.** Every w0 checkpoint carries MAML's training state (the outer Adam moments, the
//! target network, the sampling stream: [`Maml::save_state`]), so a restarted meta-learner resumes
//! meta-training from its latest w0 checkpoint exactly as an uninterrupted run continues. It skips
//! every meta-test whose last epoch is on disk; a meta-test cut short is run again from its start
//! (the fine-tuning is seeded, so to the same result), its checkpoints overwritten atomically.
//!
//! [`Maml::save_state`]: uavmeta_meta::maml::Maml::save_state

use std::path::{Path, PathBuf};
use std::time::Duration;

use iceoryx2::node::Node;
use iceoryx2::port::publisher::Publisher;
use iceoryx2::port::subscriber::Subscriber;
use iceoryx2::prelude::*;
use uavmeta_actors::policy::q_policy::Evaluator;
use uavmeta_learner::checkpoint::{self, CheckpointError};
use uavmeta_learner::progress::OnStep;
use uavmeta_learner::qnet::{QNetwork, QNetworkConfig};
use uavmeta_learner::train::{EpochRow, EvaluatePolicy, Rollouts};
use uavmeta_learner::transitions::{load_shots, Shots, Transitions};
use uavmeta_meta::context::{self, ContextModel};
use uavmeta_meta::fine_tune::{fine_tune, FineTune};
use uavmeta_meta::meta_train::{
    load_tasks, meta_train_with, MetaRow, MetaTrainHook, MetaTrainOptions,
};
use uavmeta_meta::{pretrain, MetaError};
use uavmeta_proto::config::{Config, TaskConfig};
use uavmeta_proto::dataset::Transition;
use uavmeta_proto::method::{Method, Start};
use uavmeta_proto::payload::{CheckpointReady, DatasetReady, SCHEMA_VERSION};
use uavmeta_proto::stats::PolicyMetrics;

use crate::liveness;
use crate::metrics::MetricsError;
use crate::process::Process;
use crate::run_dir::RunDir;
use crate::transport::{self, TransportError};

mod metrics;

/// The meta-learner's process name: node, port file and metrics snapshot.
pub const PROCESS: &str = "meta-learner";

const POLL: Duration = Duration::from_millis(100);

#[derive(Debug, thiserror::Error)]
pub enum MetaProcessError {
    #[error(transparent)]
    Transport(#[from] TransportError),
    #[error(transparent)]
    Metrics(#[from] MetricsError),
    #[error(transparent)]
    Meta(#[from] MetaError),
    #[error(transparent)]
    Checkpoint(#[from] CheckpointError),
}

/// How a meta-learner run ended.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Outcome {
    Finished,
    /// SIGINT/SIGTERM or a shutdown announcement; a restart resumes.
    Stopped,
}

/// Runs the meta-learner of `run`.
pub fn run(run: &RunDir, config: &Config) -> Result<Outcome, MetaProcessError> {
    let process = Process::start(run, config, PROCESS)?;
    let (node, names) = (&process.node, &process.names);
    let metrics = metrics::MetaLearnerMetrics::new();
    let _server = process.serve_metrics(run, config, metrics.registry.clone())?;
    let ready =
        transport::control_subscriber(&transport::dataset_ready_service(node, names, config)?)?;
    let announce =
        transport::control_publisher(&transport::checkpoint_ready_service(node, names, config)?)?;
    let stop = || -> Result<bool, MetaProcessError> {
        transport::serve_history(&announce)?;
        Ok(process.stop_requested(Duration::ZERO)?)
    };

    // 1. Every task's dataset.
    if !wait_for_datasets(config, node, &ready, &stop)? {
        return Ok(Outcome::Stopped);
    }
    let test_tasks: Vec<(u32, TaskConfig)> = config
        .meta_test_tasks()
        .map(|(i, t)| (i, t.clone()))
        .collect();
    let anchor = test_tasks
        .first()
        .map(|(_, t)| t.clone())
        .unwrap_or_else(|| config.tasks[0].clone());
    announce_online_agents(run, &test_tasks, &announce)?;

    // 2. Meta-training (`meta_train::meta_train_with`), resumed from the latest w0 on disk.
    let seed = config.run.seeds[0];
    let datasets = run.root().join("datasets");
    let mut hook = AnnounceW0 {
        run,
        anchor: &anchor,
        test_tasks: &test_tasks,
        publisher: &announce,
        metrics: &metrics,
        stop: &stop,
        seconds: 0.0,
    };
    let options = MetaTrainOptions {
        config,
        datasets: &datasets,
        out_dir: &run.root().join("meta-train"),
        seed,
        progress: false,
        resume: true,
        on_step: beat(),
    };
    let Some(trained) = meta_train_with(&options, &mut hook)? else {
        return Ok(Outcome::Stopped);
    };
    let (w0, meta) = checkpoint::load(&trained.w0, config)?;
    save_init(run, config, "w0", &w0, &meta.algorithm, meta.epoch)?;

    // 3. Meta-test on each unseen task (`fine_tune::fine_tune`): the MAML init fine-tuned
    //    with the loss its checkpoint names, and its baselines on the same shots.
    let meta_test = MetaTest {
        run,
        config,
        w0: &trained.w0,
        seed,
        publisher: &announce,
        metrics: &metrics,
    };
    meta_test.run_all(&test_tasks, &datasets, &stop)
}

/// The hook of every training step: a heartbeat, since an epoch over a large dataset outlasts
/// the launcher's hang timeout.
fn beat() -> OnStep {
    OnStep::new(liveness::heartbeat)
}

/// Announces the online DQN agents that made the meta-test datasets: the runs' reference line.
/// Their actors saved them before sending a transition, so a stored dataset's agent is on disk.
fn announce_online_agents(
    run: &RunDir,
    test_tasks: &[(u32, TaskConfig)],
    announce: &Publisher<ipc::Service, CheckpointReady, ()>,
) -> Result<(), TransportError> {
    for (id, task) in test_tasks {
        if checkpoint::read_meta(&run.checkpoint(Method::OnlineDqn, task, 1)).is_ok() {
            transport::announce(announce, CheckpointReady::new(Method::OnlineDqn, *id, 1))?;
        }
    }
    Ok(())
}

impl MetaTest<'_> {
    /// Fine-tunes every method of every meta-test task that has not finished, one at a time in
    /// task then method order, pretraining CQL on the meta-train shots (from `datasets`) first if
    /// a method needs it.
    fn run_all(
        &self,
        test_tasks: &[(u32, TaskConfig)],
        datasets: &Path,
        stop: &impl Fn() -> Result<bool, MetaProcessError>,
    ) -> Result<Outcome, MetaProcessError> {
        let (run, config) = (self.run, self.config);
        let epochs = config.learner.epochs as u32;
        let pending: Vec<Job> = test_tasks
            .iter()
            .flat_map(|(id, task)| {
                Method::fine_tuned(config.meta.inner_loss, &config.learner.baselines)
                    .into_iter()
                    .map(move |method| (*id, task, method))
            })
            .filter(|&(_, task, method)| latest_epoch(run, method, task, epochs) != epochs)
            .collect();
        let mut inits: Vec<MultiTaskInit> = Vec::new();
        for (id, task, method) in pending {
            if stop()? {
                return Ok(Outcome::Stopped);
            }
            if let Some(start @ (Start::Pretrain | Start::Context)) = method.start() {
                if !inits.iter().any(|init| init.start() == start) {
                    match self.multi_task_init(start, datasets, stop)? {
                        Some(init) => inits.push(init),
                        None => return Ok(Outcome::Stopped),
                    }
                }
            }
            self.fine_tune(id, task, method, &inits)?;
        }
        Ok(Outcome::Finished)
    }

    /// The init `start` names, trained on the meta-train shots (CQL on their union, or the
    /// context learner) and saved as `inits/NAME` (`inits/cql-pretrain`, `inits/cql-context`);
    /// `None` if told to stop (requests are honoured between its meta-epochs).
    fn multi_task_init(
        &self,
        start: Start,
        datasets: &Path,
        stop: &impl Fn() -> Result<bool, MetaProcessError>,
    ) -> Result<Option<MultiTaskInit>, MetaProcessError> {
        let (run, config, seed) = (self.run, self.config, self.seed);
        let name = Method::tuned(config.meta.inner_loss, start).name();
        tracing::info!(init = %name, "training on the meta-train shots");
        let (_, tasks) = load_tasks(config, datasets, seed)?;
        let keep_going = |_| stop().map(|stop| !stop);
        let init = match start {
            Start::Context => context::meta_train(config, &tasks, seed, beat(), keep_going)?
                .map(MultiTaskInit::Context),
            _ => pretrain::pretrain(config, &tasks, seed, beat(), keep_going)?
                .map(MultiTaskInit::Pretrained),
        };
        let path = run.root().join("inits").join(&name);
        match &init {
            Some(MultiTaskInit::Context(model)) => model.save(&path, config)?,
            Some(MultiTaskInit::Pretrained(q)) => {
                checkpoint::save(&path, q, &name, config.meta.meta_epochs, config)?;
            }
            None => return Ok(None),
        }
        tracing::info!(init = %path.display(), "saved");
        Ok(init)
    }
}

/// Saves an init a user fine-tunes from (`uavmeta meta-test --init` or `train --init`) where
/// they look for it: `inits/NAME` in the run directory (`inits/w0`, `inits/cql-pretrain`).
fn save_init(
    run: &RunDir,
    config: &Config,
    name: &str,
    q: &QNetwork,
    algorithm: &str,
    epoch: usize,
) -> Result<(), MetaProcessError> {
    let path = run.root().join("inits").join(name);
    checkpoint::save(&path, q, algorithm, epoch, config)?;
    tracing::info!(init = %path.display(), "saved");
    Ok(())
}

/// Waits until the store has announced every task's dataset; `false` if told to stop first.
fn wait_for_datasets(
    config: &Config,
    node: &Node<ipc::Service>,
    ready: &Subscriber<ipc::Service, DatasetReady, ()>,
    stop: &impl Fn() -> Result<bool, MetaProcessError>,
) -> Result<bool, MetaProcessError> {
    let mut waiting: Vec<bool> = vec![true; config.tasks.len()];
    tracing::info!(tasks = waiting.len(), "waiting for the datasets");
    while waiting.iter().any(|w| *w) {
        if stop()? || !liveness::keep_running(node, POLL) {
            return Ok(false);
        }
        while let Some(m) = ready
            .receive()
            .map_err(transport::receive_failed("receive a dataset announcement"))?
        {
            if let Some(w) = waiting
                .get_mut(m.task as usize)
                .filter(|_| m.schema_version == SCHEMA_VERSION)
            {
                *w = false;
            }
        }
    }
    Ok(true)
}

/// Step 3: the fine-tunings of the meta-test tasks, announcing each epoch's checkpoint.
struct MetaTest<'a> {
    run: &'a RunDir,
    config: &'a Config,
    /// The final w0 checkpoint.
    w0: &'a Path,
    seed: u64,
    publisher: &'a Publisher<ipc::Service, CheckpointReady, ()>,
    metrics: &'a metrics::MetaLearnerMetrics,
}

/// One fine-tuning of step 3: the meta-test task's number, the task, the method.
type Job<'t> = (u32, &'t TaskConfig, Method);

/// An init step 3 trains on the meta-train shots, once, when a method first needs it.
enum MultiTaskInit {
    Pretrained(QNetwork),
    Context(ContextModel),
}

impl MultiTaskInit {
    fn start(&self) -> Start {
        match self {
            MultiTaskInit::Pretrained(_) => Start::Pretrain,
            MultiTaskInit::Context(_) => Start::Context,
        }
    }
}

impl MetaTest<'_> {
    /// Fine-tunes `method`'s init on the shots of meta-test task `task` (number `task_id`),
    /// announcing every epoch's checkpoint.
    fn fine_tune(
        &self,
        task_id: u32,
        task: &TaskConfig,
        method: Method,
        inits: &[MultiTaskInit],
    ) -> Result<(), MetaProcessError> {
        let shots = self.shots(task)?;
        let mut hook = self.hook(task_id, task, method, &shots);
        let mut q = self.init(method, &shots.data, inits)?;
        if method.start() == Some(Start::Context) {
            // The context learner's policy before any step: its zero-shot row.
            self.publish(task_id, task, Method::ContextInit, 1, &q)?;
        }
        let algorithm = method.algo().expect("a fine-tuned method has an algorithm");
        let rows = fine_tune(
            &mut q,
            &shots.data,
            algorithm,
            &self.settings(task),
            &mut hook,
        )?;
        self.finished(&mut hook, task, method, &rows)
    }

    /// The network `method` fine-tunes on `shots`: w0, the pretrained network, the context
    /// learner's policy for the shots' task code, or a random init.
    fn init(
        &self,
        method: Method,
        shots: &Transitions,
        inits: &[MultiTaskInit],
    ) -> Result<QNetwork, MetaProcessError> {
        let config = self.config;
        let trained = inits
            .iter()
            .find(|init| Some(init.start()) == method.start());
        Ok(match (method.start(), trained) {
            (Some(Start::Maml | Start::W0), _) => {
                check_init(self.w0, Method::maml(config.meta.inner_loss))?;
                checkpoint::load(self.w0, config)?.0
            }
            (_, Some(MultiTaskInit::Pretrained(q))) => q.duplicate(),
            (_, Some(MultiTaskInit::Context(model))) => model.policy(shots),
            // The init's seed is the run's + 1, the shots' the run's: `uavmeta train --seed S
            // --init-seed S+1` is this run (kept so that earlier tables stay reproducible).
            _ => QNetworkConfig::for_world(&config.world, &config.learner.hidden)
                .init(self.seed.wrapping_add(1)),
        })
    }

    /// Saves `q` as `method`'s checkpoint of epoch `epoch` on meta-test task `task` (number
    /// `task_id`) and announces it.
    fn publish(
        &self,
        task_id: u32,
        task: &TaskConfig,
        method: Method,
        epoch: u32,
        q: &QNetwork,
    ) -> Result<(), MetaProcessError> {
        let path = self.run.checkpoint(method, task, epoch);
        checkpoint::save(&path, q, &method.name(), epoch as usize, self.config)?;
        transport::announce(self.publisher, CheckpointReady::new(method, task_id, epoch))?;
        self.metrics.checkpoints.inc();
        Ok(())
    }

    /// The task's `learner.shots` shots (all of its dataset by default), drawn with the run's seed.
    fn shots(&self, task: &TaskConfig) -> Result<Shots, MetaProcessError> {
        let config = self.config;
        let dataset = self.run.dataset(task);
        Ok(
            load_shots(config, task, &dataset, config.fine_tune_shots(), self.seed)
                .map_err(MetaError::from)?,
        )
    }

    fn settings<'t>(&'t self, task: &'t TaskConfig) -> FineTune<'t> {
        FineTune {
            config: self.config,
            task,
            epochs: self.config.learner.epochs,
            seed: self.seed,
            out_dir: None,
            progress: false,
            on_step: beat(),
        }
    }

    /// The evaluator of a fine-tuning on `shots`, which checkpoints and announces each epoch.
    fn hook<'t>(
        &'t self,
        task_id: u32,
        task: &'t TaskConfig,
        method: Method,
        shots: &Shots,
    ) -> Announcing<'t> {
        Announcing {
            inner: Evaluator::from_config(self.config, task).with_model(&shots.rows),
            meta_test: self,
            task,
            task_id,
            method,
            epoch: 0,
            error: None,
        }
    }

    /// The hook's first failure, else a log line.
    fn finished(
        &self,
        hook: &mut Announcing,
        task: &TaskConfig,
        method: Method,
        rows: &[EpochRow],
    ) -> Result<(), MetaProcessError> {
        if let Some(error) = hook.error.take() {
            return Err(error);
        }
        if let Some(last) = rows.last() {
            tracing::info!(task = %task.name, %method, epochs = rows.len(), ret = last.policy.ret.mean, "meta-test done");
        }
        Ok(())
    }
}

/// The w0 checkpoint is the one `method` fine-tunes: a run directory meta-trained with another
/// `meta.inner_loss` is refused rather than reported under the wrong name.
fn check_init(w0: &Path, method: Method) -> Result<(), MetaProcessError> {
    let algorithm = checkpoint::read_meta(w0)?.algorithm;
    match algorithm == method.name() {
        true => Ok(()),
        false => Err(MetaError::NotMetaTrained {
            path: w0.to_path_buf(),
            algorithm,
        }
        .into()),
    }
}

/// Meta-training's hook: exports each meta-epoch's figures, announces each w0 checkpoint to every
/// meta-test task's evaluator, and stops on request.
struct AnnounceW0<'a, S> {
    run: &'a RunDir,
    anchor: &'a TaskConfig,
    test_tasks: &'a [(u32, TaskConfig)],
    publisher: &'a Publisher<ipc::Service, CheckpointReady, ()>,
    metrics: &'a metrics::MetaLearnerMetrics,
    stop: &'a S,
    /// `MetaRow::seconds` of the previous meta-epoch.
    seconds: f64,
}

impl<S: Fn() -> Result<bool, MetaProcessError>> MetaTrainHook for AnnounceW0<'_, S> {
    type Error = MetaProcessError;

    fn checkpoint_path(&self, epoch: usize) -> PathBuf {
        self.run
            .checkpoint(Method::MetaInit, self.anchor, epoch as u32)
    }

    fn after_epoch(
        &mut self,
        row: &MetaRow,
        checkpoint: Option<&Path>,
    ) -> Result<bool, Self::Error> {
        let epoch = row.epoch.epoch as u32;
        self.metrics
            .meta_epoch_duration
            .observe((row.seconds - self.seconds).max(0.0));
        self.seconds = row.seconds;
        self.metrics.meta_epoch.set(epoch as i64);
        self.metrics.meta_loss.set(row.epoch.meta_loss);
        if checkpoint.is_some() {
            self.metrics.checkpoints.inc();
            for (id, _) in self.test_tasks {
                let message = CheckpointReady::new(Method::MetaInit, *id, epoch);
                transport::announce(self.publisher, message)?;
            }
            tracing::info!(epoch, meta_loss = row.epoch.meta_loss, "w0 checkpoint");
        }
        Ok(!(self.stop)()?)
    }
}

/// The highest epoch (at most `max`) whose checkpoint of `method` on `task` is complete on disk.
fn latest_epoch(run: &RunDir, method: Method, task: &TaskConfig, max: u32) -> u32 {
    (1..=max)
        .rev()
        .find(|&epoch| checkpoint::read_meta(&run.checkpoint(method, task, epoch)).is_ok())
        .unwrap_or(0)
}

/// The fine-tuning hook: after every epoch, checkpoint and announce the network, then score it.
struct Announcing<'a> {
    inner: Evaluator,
    meta_test: &'a MetaTest<'a>,
    task: &'a TaskConfig,
    task_id: u32,
    method: Method,
    epoch: u32,
    /// The first failure; training cannot be interrupted from inside the hook.
    error: Option<MetaProcessError>,
}

impl EvaluatePolicy for Announcing<'_> {
    fn evaluate(&mut self, q: &QNetwork) -> PolicyMetrics {
        liveness::heartbeat();
        self.epoch += 1;
        self.meta_test.metrics.fine_tune_epochs.inc();
        if self.error.is_none() {
            let published =
                self.meta_test
                    .publish(self.task_id, self.task, self.method, self.epoch, q);
            self.error = published.err();
        }
        self.inner.evaluate(q)
    }

    fn rollouts(&mut self, q: &QNetwork, ask: Rollouts) -> Option<Vec<Transition>> {
        self.inner.rollouts(q, ask)
    }
}
