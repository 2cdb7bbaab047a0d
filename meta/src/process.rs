//! The meta-learner process (`uavmeta meta-learner --run R`): MAML over the run's datasets as
//! soon as the store announces them, then meta-test on the unseen task(s).
//!
//! 1. Waits until the store has announced the dataset of every task (meta-train tasks for MAML,
//!    meta-test tasks for their few shots).
//! 2. Meta-trains w0 with [`Maml::meta_epoch`] (Algorithm 4) for `meta.meta_epochs` meta-epochs;
//!    every `meta.checkpoint_every` meta-epochs (and after the last) it writes w0 as a checkpoint
//!    (`uavmeta_learner::checkpoint`: write, fsync, rename) and announces it once per meta-test
//!    task, whose evaluator then scores it zero-shot.
//!    Before that it announces each meta-test task's online DQN agent (saved by its actor), the
//!    reference line.
//! 3. Meta-tests: per meta-test task, fine-tunes w0 with CQL on `collect.transitions` shots
//!    (CQL-MAML) and, as baselines, CQL from a random init and from a CQL network pretrained on
//!    the union of the meta-train tasks' shots (CQL-pretrain, `crate::pretrain`) on the same
//!    shots, each for `learner.epochs` epochs (the settings of `meta_test::fine_tune`),
//!    checkpointing and announcing every epoch.
//!
//! **Restart.** Every w0 checkpoint carries MAML's training state (the outer Adam moments, the
//! target network, the sampling stream: [`Maml::save_state`]), so a restarted meta-learner resumes
//! meta-training from its latest w0 checkpoint exactly as an uninterrupted run continues. It skips
//! every meta-test whose last epoch is on disk; a meta-test cut short is run again from its start
//! (the fine-tuning is seeded, so to the same result), its checkpoints overwritten atomically.

use std::time::{Duration, Instant};

use iceoryx2::port::publisher::Publisher;
use iceoryx2::prelude::*;
use uavmeta_actors::q_policy::Evaluator;
use uavmeta_learner::checkpoint::{self, CheckpointError};
use uavmeta_learner::metrics::{MetricsError, MetricsServer};
use uavmeta_learner::qnet::QNetwork;
use uavmeta_learner::train::{train, Algorithm, EvaluatePolicy, TrainOptions};
use uavmeta_proto::config::{Config, TaskConfig, TaskRole};
use uavmeta_proto::stats::PolicyMetrics;
use uavmeta_proto::transport::{
    self, CheckpointReady, Method, RunDir, ServiceNames, TransportError, SCHEMA_VERSION,
};

use crate::maml::{Maml, MamlConfig};
use crate::meta_test::load_shots;
use crate::meta_train::{algorithm_name, load_tasks};
use crate::{pretrain, MetaError};

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

/// The meta-learner's metrics: every name it exports, in one place.
mod metrics {
    use prometheus::{Gauge, Histogram, IntCounter, IntGauge, Opts, Registry};
    use uavmeta_learner::metrics::{counter, latency_histogram, register};

    pub struct MetaLearnerMetrics {
        pub registry: Registry,
        pub meta_epoch: IntGauge,
        pub meta_loss: Gauge,
        pub meta_epoch_duration: Histogram,
        pub checkpoints: IntCounter,
        pub fine_tune_epochs: IntCounter,
    }

    impl MetaLearnerMetrics {
        pub fn new() -> Self {
            let registry = uavmeta_learner::metrics::registry();
            Self {
                meta_epoch: register(&registry, IntGauge::with_opts(Opts::new("meta_learner_meta_epoch", "Meta-epochs behind w0.")).expect("valid gauge")),
                meta_loss: register(&registry, Gauge::with_opts(Opts::new("meta_learner_meta_loss", "Meta-loss (sum of the adapted weights' query losses) of the last meta-epoch.")).expect("valid gauge")),
                meta_epoch_duration: latency_histogram(&registry, "meta_learner_meta_epoch_duration_seconds", "Time of one meta-epoch."),
                checkpoints: counter(&registry, "meta_learner_checkpoints_written_total", "Checkpoints written and announced."),
                fine_tune_epochs: counter(&registry, "meta_learner_fine_tune_epochs_total", "Meta-test fine-tuning epochs run."),
                registry,
            }
        }
    }
}

/// Runs the meta-learner of `run`.
pub fn run(run: &RunDir, config: &Config) -> Result<Outcome, MetaProcessError> {
    let node = transport::node(&format!("{}-{PROCESS}", run.id()))?;
    let names = ServiceNames::new(run);
    let metrics = metrics::MetaLearnerMetrics::new();
    let _server = MetricsServer::start(
        metrics.registry.clone(),
        &config.run.metrics_host,
        0,
        run,
        PROCESS,
    )?;
    let ready = transport::control_subscriber(
        &transport::dataset_ready_service(&node, &names, config)?,
        config,
    )?;
    let shutdown = transport::control_subscriber(
        &transport::shutdown_service(&node, &names, config)?,
        config,
    )?;
    let announce =
        transport::control_publisher(&transport::checkpoint_ready_service(&node, &names, config)?)?;
    let stop = || -> Result<bool, MetaProcessError> {
        transport::serve_history(&announce)?;
        let signalled = !transport::keep_running(&node, Duration::ZERO);
        Ok(transport::shutdown_requested(&shutdown)? || signalled)
    };

    // 1. Every task's dataset.
    let mut waiting: Vec<bool> = vec![true; config.tasks.len()];
    tracing::info!(tasks = waiting.len(), "waiting for the datasets");
    while waiting.iter().any(|w| *w) {
        if stop()? || !transport::keep_running(&node, POLL) {
            return Ok(Outcome::Stopped);
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
    let test_tasks: Vec<(u32, TaskConfig)> = config
        .tasks
        .iter()
        .enumerate()
        .filter(|(_, t)| t.role == TaskRole::MetaTest)
        .map(|(i, t)| (i as u32, t.clone()))
        .collect();
    let anchor = test_tasks
        .first()
        .map(|(_, t)| t.clone())
        .unwrap_or_else(|| config.tasks[0].clone());

    // The online DQN agents that made the meta-test datasets: the runs' reference line. Their
    // actors saved them before sending a transition, so a stored dataset's agent is on disk.
    for (id, task) in &test_tasks {
        if checkpoint::read_meta(&run.checkpoint(Method::OnlineDqn, task, 1)).is_ok() {
            transport::announce(
                &announce,
                CheckpointReady {
                    schema_version: SCHEMA_VERSION,
                    method: Method::OnlineDqn.code(),
                    task: *id,
                    epoch: 1,
                },
            )?;
        }
    }

    // 2. Meta-training, resumed from the latest w0 on disk.
    let seed = config.run.seeds[0];
    let (_, tasks) = load_tasks(config, &run.root().join("datasets"), seed)?;
    let final_epoch = config.meta.meta_epochs as u32;
    let start_epoch = latest_epoch(run, Method::MetaInit, &anchor, final_epoch);
    let mut maml = match start_epoch {
        0 => Maml::new(
            QNetwork::new(
                config.world.observation_len(),
                config.world.action_count(),
                &config.learner.hidden,
                seed,
            ),
            MamlConfig::from_config(config),
            seed,
        )?,
        epoch => {
            tracing::info!(epoch, "resuming meta-training from its checkpoint");
            let path = run.checkpoint(Method::MetaInit, &anchor, epoch);
            let w0 = checkpoint::load(&path, config)?.0;
            Maml::resume(w0, MamlConfig::from_config(config), &path)?
        }
    };
    metrics.meta_epoch.set(start_epoch as i64);
    for epoch in start_epoch + 1..=final_epoch {
        if stop()? {
            return Ok(Outcome::Stopped);
        }
        let start = Instant::now();
        let figures = maml.meta_epoch(&tasks)?;
        metrics
            .meta_epoch_duration
            .observe(start.elapsed().as_secs_f64());
        metrics.meta_epoch.set(epoch as i64);
        metrics.meta_loss.set(figures.meta_loss);
        if epoch % config.meta.checkpoint_every as u32 == 0 || epoch == final_epoch {
            let path = run.checkpoint(Method::MetaInit, &anchor, epoch);
            // The state first: the checkpoint's metadata, written last, marks both complete.
            maml.save_state(&path)?;
            checkpoint::save(
                &path,
                maml.w0(),
                algorithm_name(config.meta.inner_loss),
                epoch as usize,
                config,
            )?;
            metrics.checkpoints.inc();
            for (id, _) in &test_tasks {
                transport::announce(
                    &announce,
                    CheckpointReady {
                        schema_version: SCHEMA_VERSION,
                        method: Method::MetaInit.code(),
                        task: *id,
                        epoch,
                    },
                )?;
            }
            tracing::info!(epoch, meta_loss = figures.meta_loss, "w0 checkpoint");
        }
    }
    let w0_path = run.checkpoint(Method::MetaInit, &anchor, final_epoch);

    // 3. Meta-test on each unseen task: CQL-MAML from w0, CQL from a random init, and
    //    CQL-pretrain from one CQL network trained on the union of the meta-train shots.
    let epochs = config.learner.epochs as u32;
    let mut pretrained: Option<QNetwork> = None;
    for (id, task) in &test_tasks {
        for method in Method::FINE_TUNED {
            if latest_epoch(run, method, task, epochs) == epochs {
                continue;
            }
            if stop()? {
                return Ok(Outcome::Stopped);
            }
            if method == Method::CqlPretrain && pretrained.is_none() {
                tracing::info!("pretraining CQL on the union of the meta-train shots");
                // Stop requests are honoured between the pretraining's meta-epochs.
                match pretrain::pretrain(config, &tasks, seed, |_| stop().map(|stop| !stop))? {
                    Some(q) => pretrained = Some(q),
                    None => return Ok(Outcome::Stopped),
                }
            }
            let mut q = match (method, &pretrained) {
                (Method::CqlMaml, _) => checkpoint::load(&w0_path, config)?.0,
                (Method::CqlPretrain, Some(pretrained)) => pretrained.duplicate(),
                _ => QNetwork::new(
                    config.world.observation_len(),
                    config.world.action_count(),
                    &config.learner.hidden,
                    seed.wrapping_add(1),
                ),
            };
            let shots = load_shots(
                config,
                task,
                &run.dataset(task),
                config.collect.transitions,
                seed,
            )?;
            let mut hook = Announcing {
                inner: Evaluator::from_config(config, task),
                run,
                config,
                task,
                task_id: *id,
                method,
                publisher: &announce,
                epoch: 0,
                error: None,
                metrics: &metrics,
            };
            // The fine-tuning of `meta_test::fine_tune`, with this process's hook as its evaluator.
            let options = TrainOptions {
                algorithm: Algorithm::Cql,
                config,
                seed,
                out_dir: None,
                progress: false,
            };
            let rows = train(&mut q, &shots, &options, &mut hook).map_err(MetaError::from)?;
            if let Some(error) = hook.error {
                return Err(error);
            }
            if let Some(last) = rows.last() {
                tracing::info!(task = %task.name, %method, epochs = rows.len(), ret = last.policy.ret.mean, "meta-test done");
            }
        }
    }
    Ok(Outcome::Finished)
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
    run: &'a RunDir,
    config: &'a Config,
    task: &'a TaskConfig,
    task_id: u32,
    method: Method,
    publisher: &'a Publisher<ipc::Service, CheckpointReady, ()>,
    epoch: u32,
    /// The first failure; training cannot be interrupted from inside the hook.
    error: Option<MetaProcessError>,
    metrics: &'a metrics::MetaLearnerMetrics,
}

impl EvaluatePolicy for Announcing<'_> {
    fn evaluate(&mut self, q: &QNetwork) -> PolicyMetrics {
        self.epoch += 1;
        self.metrics.fine_tune_epochs.inc();
        if self.error.is_none() {
            let path = self.run.checkpoint(self.method, self.task, self.epoch);
            let saved = checkpoint::save(
                &path,
                q,
                self.method.name(),
                self.epoch as usize,
                self.config,
            )
            .map_err(MetaProcessError::from)
            .and_then(|_| {
                let message = CheckpointReady {
                    schema_version: SCHEMA_VERSION,
                    method: self.method.code(),
                    task: self.task_id,
                    epoch: self.epoch,
                };
                Ok(transport::announce(self.publisher, message)?)
            });
            match saved {
                Ok(_) => self.metrics.checkpoints.inc(),
                Err(error) => self.error = Some(error),
            }
        }
        self.inner.evaluate(q)
    }
}
