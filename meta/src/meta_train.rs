//! Meta-training from datasets (`uavmeta meta-train`): MAML ([`crate::maml`]) over the config's
//! meta-train tasks, each read from `<datasets>/<task-name>.uavds`.
//!
//! Each task's file is split once into a support set and a query set (`meta.support_fraction`,
//! seeded); every meta-epoch then runs [`Maml::meta_epoch`]. The run writes into its output
//! directory:
//! - `config.toml`: the full config, first, so the directory alone reproduces the run;
//! - `meta_train.csv`: one row per meta-epoch with the meta-loss (eq. 15), each task's query loss
//!   (empty when the task was not sampled that meta-epoch) and, every `meta.eval_every`
//!   meta-epochs and after the last, each task's greedy return after adaptation (eq. 14 on k
//!   fresh support shots) measured on its true environment;
//! - `w0-eNNNN.*` every `meta.checkpoint_every` meta-epochs and `w0.*` at the end: checkpoints of
//!   the meta-learned initial weights (`uavmeta_learner::checkpoint`), the `--init` of meta-test.

use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};
use std::time::Instant;

use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use uavmeta_actors::q_policy::Evaluator;
use uavmeta_learner::batch::Batch;
use uavmeta_learner::checkpoint;
use uavmeta_learner::qnet::QNetwork;
use uavmeta_learner::train::EvaluatePolicy;
use uavmeta_proto::config::{Config, InnerLoss, TaskConfig, TaskRole};
use uavmeta_proto::dataset::{self, DatasetReader};

use crate::maml::{Maml, MamlConfig, MetaEpoch, MetaTask};
use crate::MetaError;

/// One meta-training run.
pub struct MetaTrainOptions<'a> {
    /// `[meta]` and `[learner]` drive the run; `[[tasks]]` with role `meta-train` name the tasks.
    pub config: &'a Config,
    /// Holds `<task-name>.uavds` for every meta-train task.
    pub datasets: &'a Path,
    pub out_dir: &'a Path,
    /// Seed of w0's initialisation, the support/query split, and task and shot sampling.
    pub seed: u64,
    /// Draw a progress bar on stderr.
    pub progress: bool,
}

/// One meta-epoch's figures.
#[derive(Debug, Clone, PartialEq)]
pub struct MetaRow {
    pub epoch: MetaEpoch,
    /// Per task (config order among meta-train tasks): the greedy return after adaptation, in
    /// evaluated meta-epochs.
    pub returns: Option<Vec<f64>>,
    /// Wall-clock seconds since meta-training started.
    pub seconds: f64,
}

/// What a finished run left behind.
pub struct MetaTrainResult {
    pub tasks: Vec<TaskConfig>,
    pub rows: Vec<MetaRow>,
    /// The final w0 checkpoint (`uavmeta meta-test --init`).
    pub w0: PathBuf,
}

/// The checkpoint algorithm name of a MAML run: `cql-maml` or `dqn-maml`.
pub fn algorithm_name(inner_loss: InnerLoss) -> &'static str {
    match inner_loss {
        InnerLoss::Cql => "cql-maml",
        InnerLoss::Dqn => "dqn-maml",
    }
}

/// The dataset file of `task` in a datasets directory.
pub fn dataset_path(datasets: &Path, task: &str) -> PathBuf {
    datasets.join(format!("{task}.{}", dataset::FILE_EXTENSION))
}

/// Reads every meta-train task's dataset, checks it belongs to this world and task, and splits it
/// into encoded support and query sets.
pub fn load_tasks(
    config: &Config,
    datasets: &Path,
    seed: u64,
) -> Result<(Vec<TaskConfig>, Vec<MetaTask>), MetaError> {
    let tasks: Vec<TaskConfig> = config
        .tasks_with_role(TaskRole::MetaTrain)
        .cloned()
        .collect();
    if tasks.is_empty() {
        return Err(MetaError::NoMetaTrainTasks {
            origin: config.origin.clone(),
        });
    }
    let mut meta_tasks = Vec::with_capacity(tasks.len());
    for (i, task) in tasks.iter().enumerate() {
        let path = dataset_path(datasets, &task.name);
        let reader = DatasetReader::open(&path)?;
        reader.check_world(config)?;
        if reader.header().task_name != task.name {
            return Err(MetaError::WrongTask {
                path,
                found: reader.header().task_name.clone(),
                expected: task.name.clone(),
            });
        }
        // One split stream per task, so adding a task leaves the others' splits unchanged.
        let (support, query) = dataset::split(
            reader.transitions(),
            config.meta.support_fraction,
            seed.wrapping_add(i as u64),
        )?;
        let encode = |set: &[_]| {
            Batch::new(set, &config.world, config.learner.reward_scale).map_err(|source| {
                MetaError::Batch {
                    path: path.clone(),
                    source,
                }
            })
        };
        meta_tasks.push(MetaTask {
            name: task.name.clone(),
            support: encode(&support)?,
            query: encode(&query)?,
        });
    }
    Ok((tasks, meta_tasks))
}

/// Runs `meta.meta_epochs` meta-epochs; see the module doc for what it writes.
pub fn meta_train(opts: &MetaTrainOptions) -> Result<MetaTrainResult, MetaError> {
    let config = opts.config;
    let meta = &config.meta;
    let (tasks, meta_tasks) = load_tasks(config, opts.datasets, opts.seed)?;
    let out = opts.out_dir;
    std::fs::create_dir_all(out).map_err(|source| MetaError::Io {
        path: out.to_path_buf(),
        action: "create",
        source,
    })?;
    let config_path = out.join("config.toml");
    std::fs::write(&config_path, config.to_toml_string()).map_err(|source| MetaError::Io {
        path: config_path,
        action: "write",
        source,
    })?;
    let mut csv = CsvLog::create(&out.join("meta_train.csv"), &tasks)?;

    let w0 = QNetwork::new(
        config.world.observation_len(),
        config.world.action_count(),
        &config.learner.hidden,
        opts.seed,
    );
    let mut maml = Maml::new(w0, MamlConfig::from_config(config), opts.seed)?;
    let mut evaluators: Vec<Evaluator> = tasks
        .iter()
        .map(|t| Evaluator::from_config(config, t))
        .collect();
    let algorithm = algorithm_name(meta.inner_loss);

    let bar = progress_bar(opts.progress, meta.meta_epochs as u64);
    let started = Instant::now();
    let mut rows = Vec::with_capacity(meta.meta_epochs);
    for e in 1..=meta.meta_epochs {
        let epoch = maml.meta_epoch(&meta_tasks)?;
        let evaluate = e == meta.meta_epochs || (meta.eval_every > 0 && e % meta.eval_every == 0);
        let returns = evaluate.then(|| {
            meta_tasks
                .iter()
                .zip(&mut evaluators)
                .enumerate()
                .map(|(i, (task, evaluator))| {
                    // Shots of their own stream, so the evaluation interval leaves training unchanged.
                    let mut rng =
                        ChaCha8Rng::seed_from_u64(opts.seed ^ ((e as u64) << 32) ^ i as u64);
                    let shots = task.sample(meta.shots, meta.query_shots, &mut rng);
                    evaluator.evaluate(&maml.adapted(&shots.support)).ret.mean
                })
                .collect::<Vec<f64>>()
        });
        let row = MetaRow {
            epoch,
            returns,
            seconds: started.elapsed().as_secs_f64(),
        };
        csv.write(&row, tasks.len())?;
        bar.set_message(format!("meta-loss {:.4}", row.epoch.meta_loss));
        if let Some(returns) = &row.returns {
            let mean = returns.iter().sum::<f64>() / returns.len() as f64;
            bar.suspend(|| {
                tracing::info!(
                    meta_epoch = e,
                    meta_loss = row.epoch.meta_loss,
                    mean_return = mean,
                    "adapted greedy returns"
                )
            });
        }
        bar.inc(1);
        rows.push(row);
        if e % meta.checkpoint_every == 0 {
            checkpoint::save(
                &out.join(format!("w0-e{e:04}")),
                maml.w0(),
                algorithm,
                e,
                config,
            )?;
        }
    }
    bar.finish_and_clear();
    let w0 = out.join("w0");
    checkpoint::save(&w0, maml.w0(), algorithm, meta.meta_epochs, config)?;
    Ok(MetaTrainResult { tasks, rows, w0 })
}

fn progress_bar(enabled: bool, len: u64) -> ProgressBar {
    if !enabled {
        return ProgressBar::with_draw_target(Some(len), ProgressDrawTarget::hidden());
    }
    ProgressBar::new(len).with_style(
        ProgressStyle::with_template("{bar:40} {pos}/{len} meta-epochs {msg} eta {eta}")
            .expect("the template is valid"),
    )
}

/// `meta_train.csv`, flushed row by row so an interrupted run keeps what it did.
struct CsvLog {
    path: PathBuf,
    file: BufWriter<File>,
}

impl CsvLog {
    fn create(path: &Path, tasks: &[TaskConfig]) -> Result<Self, MetaError> {
        let file = File::create(path).map_err(|source| MetaError::Io {
            path: path.to_path_buf(),
            action: "create",
            source,
        })?;
        let mut log = Self {
            path: path.to_path_buf(),
            file: BufWriter::new(file),
        };
        let mut header = String::from("meta_epoch,meta_loss");
        for t in tasks {
            header.push_str(&format!(",loss_{}", t.name));
        }
        for t in tasks {
            header.push_str(&format!(",return_{}", t.name));
        }
        header.push_str(",seconds");
        log.line(&header)?;
        Ok(log)
    }

    fn write(&mut self, row: &MetaRow, tasks: usize) -> Result<(), MetaError> {
        let mut losses = vec![String::new(); tasks];
        for &(task, loss) in &row.epoch.task_losses {
            losses[task] = loss.to_string();
        }
        let returns = match &row.returns {
            Some(r) => r.iter().map(f64::to_string).collect(),
            None => vec![String::new(); tasks],
        };
        let line = format!(
            "{},{},{},{},{:.3}",
            row.epoch.epoch,
            row.epoch.meta_loss,
            losses.join(","),
            returns.join(","),
            row.seconds
        );
        self.line(&line)
    }

    fn line(&mut self, line: &str) -> Result<(), MetaError> {
        writeln!(self.file, "{line}")
            .and_then(|()| self.file.flush())
            .map_err(|source| MetaError::Io {
                path: self.path.clone(),
                action: "write",
                source,
            })
    }
}
