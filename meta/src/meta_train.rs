//! Meta-training from datasets (`uavmeta meta-train`): MAML ([`crate::maml`]) over the config's
//! meta-train tasks, each read from `<datasets>/<task-name>.uavds`.
//!
//! Each task's file is split once into a support set and a query set (`meta.support_fraction`,
//! seeded); every meta-epoch then runs [`Maml::meta_epoch`]. The run writes into its output
//! directory:
//! - `config.toml`: the full config, first, so the directory alone reproduces the run;
//! - `meta_train.csv`: one row per meta-epoch with the meta-loss (eq. 15), each task's query loss
//!   (empty when the task was not sampled that meta-epoch) and, every `meta.eval_every`
//!   meta-epochs and after the last, each task's greedy return on its true environment after
//!   adaptation (eq. 14 on k fresh support shots, averaged over `meta.eval_adaptations`
//!   adaptations) and, as the reference it is measured against, w0's own with no adaptation;
//! - `w0-eNNNN.*` every `meta.checkpoint_every` meta-epochs and `w0.*` after the last: checkpoints
//!   of the meta-learned initial weights (`uavmeta_learner::checkpoint`), the `--init` of
//!   meta-test, each with MAML's training state beside it ([`Maml::save_state`]), so a run
//!   started again with `resume` continues from its latest checkpoint exactly as an
//!   uninterrupted run does.
//!
//! The meta-learner process runs the same loop through [`meta_train_with`], with a hook that
//! puts the checkpoints into its run directory and announces them.

use std::path::{Path, PathBuf};
use std::time::Instant;

use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use uavmeta_actors::policy::q_policy::Evaluator;
use uavmeta_learner::algorithm;
use uavmeta_learner::checkpoint;
use uavmeta_learner::progress::{progress_bar, CsvLog, OnStep};
use uavmeta_learner::qnet::QNetworkConfig;
use uavmeta_learner::train::EvaluatePolicy;
use uavmeta_learner::transitions::Transitions;
use uavmeta_proto::config::{Config, MetaConfig, TaskConfig, TaskRole};
use uavmeta_proto::dataset::{self, DatasetReader};
use uavmeta_proto::method::Method;

use crate::maml::{Maml, MamlConfig, MetaEpoch, MetaTask};
use crate::{create_dir, write_file, MetaError};

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
    /// Continue from the latest complete checkpoint the hook names, if there is one.
    pub resume: bool,
    /// Called at every outer step of MAML.
    pub on_step: OnStep,
}

/// One meta-epoch's figures.
#[derive(Debug, Clone, PartialEq)]
pub struct MetaRow {
    pub epoch: MetaEpoch,
    /// Each task's greedy returns, in evaluated meta-epochs.
    pub evaluation: Option<Evaluation>,
    /// Wall-clock seconds since meta-training started.
    pub seconds: f64,
}

/// One evaluation of every meta-train task (config order): w0's greedy return after adaptation,
/// and with none.
#[derive(Debug, Clone, PartialEq)]
pub struct Evaluation {
    pub adapted: Vec<f64>,
    /// What the adaptation is measured against: w0 itself, zero-shot.
    pub zero_shot: Vec<f64>,
}

/// What a finished run left behind.
pub struct MetaTrainResult {
    pub tasks: Vec<TaskConfig>,
    /// The meta-epochs this call ran (after the resumed checkpoint's, when resuming).
    pub rows: Vec<MetaRow>,
    /// The final w0 checkpoint (`uavmeta meta-test --init`).
    pub w0: PathBuf,
}

/// Where a meta-training run keeps its w0 checkpoints, and who hears of each meta-epoch.
pub trait MetaTrainHook {
    type Error: From<MetaError>;
    /// The checkpoint of w0 after meta-epoch `epoch`.
    fn checkpoint_path(&self, epoch: usize) -> PathBuf;
    /// After every meta-epoch, with the checkpoint written after it, if any; `Ok(false)` ends
    /// the run there (resumable from its latest checkpoint).
    fn after_epoch(
        &mut self,
        row: &MetaRow,
        checkpoint: Option<&Path>,
    ) -> Result<bool, Self::Error>;
}

/// The CLI's checkpoints: `w0-eNNNN` in the output directory, and `w0` after the last meta-epoch.
pub struct CheckpointFiles<'a> {
    pub out_dir: &'a Path,
    pub meta_epochs: usize,
}

impl MetaTrainHook for CheckpointFiles<'_> {
    type Error = MetaError;

    fn checkpoint_path(&self, epoch: usize) -> PathBuf {
        match epoch == self.meta_epochs {
            true => self.out_dir.join("w0"),
            false => self.out_dir.join(format!("w0-e{epoch:04}")),
        }
    }

    fn after_epoch(&mut self, _: &MetaRow, _: Option<&Path>) -> Result<bool, MetaError> {
        Ok(true)
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
        let reader = DatasetReader::open_task(&path, config, &task.name)?;
        // One split stream per task, so adding a task leaves the others' splits unchanged.
        let (support, query) = dataset::split(
            reader.transitions(),
            config.meta.support_fraction,
            seed.wrapping_add(i as u64),
        )?;
        let encode = |set: &[_]| {
            Transitions::new(set, &config.world, config.learner.reward_scale).map_err(|source| {
                MetaError::Transitions {
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

/// Runs `meta.meta_epochs` meta-epochs with the CLI's checkpoint files; see the module doc for
/// what it writes.
pub fn meta_train(opts: &MetaTrainOptions) -> Result<MetaTrainResult, MetaError> {
    let mut files = CheckpointFiles {
        out_dir: opts.out_dir,
        meta_epochs: opts.config.meta.meta_epochs,
    };
    Ok(meta_train_with(opts, &mut files)?.expect("the checkpoint files never stop a run"))
}

/// Runs meta-training up to `meta.meta_epochs` meta-epochs, checkpointing w0 where `hook` says
/// every `meta.checkpoint_every` meta-epochs and after the last; `None` when the hook stopped it.
pub fn meta_train_with<H: MetaTrainHook>(
    opts: &MetaTrainOptions,
    hook: &mut H,
) -> Result<Option<MetaTrainResult>, H::Error> {
    let meta = &opts.config.meta;
    let mut log = RunLog::open(opts)?;
    let (maml, start) = start_or_resume(opts, hook)?;
    let mut maml = maml.with_on_step(opts.on_step.clone());
    log.open_csv(start)?;
    let bar = progress_bar(
        opts.progress,
        meta.meta_epochs as u64,
        "{bar:40} {pos}/{len} meta-epochs {msg} eta {eta}",
    );
    bar.set_position(start as u64);
    let started = Instant::now();
    let mut rows = Vec::new();
    for e in start + 1..=meta.meta_epochs {
        let epoch = maml.meta_epoch(&log.meta_tasks)?;
        let checkpoint = is_checkpoint_epoch(meta, e).then(|| hook.checkpoint_path(e));
        let row = bar.suspend(|| log.after_epoch(&maml, epoch, checkpoint.as_deref(), started))?;
        bar.set_message(format!("meta-loss {:.4}", row.epoch.meta_loss));
        bar.inc(1);
        let keep_going = hook.after_epoch(&row, checkpoint.as_deref())?;
        rows.push(row);
        if !keep_going {
            return Ok(None);
        }
    }
    bar.finish_and_clear();
    let w0 = hook.checkpoint_path(meta.meta_epochs);
    Ok(Some(MetaTrainResult {
        tasks: log.tasks,
        rows,
        w0,
    }))
}

/// One run's tasks, the evaluators of their environments and its `meta_train.csv`.
struct RunLog<'a> {
    opts: &'a MetaTrainOptions<'a>,
    tasks: Vec<TaskConfig>,
    meta_tasks: Vec<MetaTask>,
    evaluators: Vec<Evaluator>,
    csv: Option<CsvLog>,
}

impl<'a> RunLog<'a> {
    /// Reads the run's tasks, and creates its output directory with its `config.toml`.
    fn open(opts: &'a MetaTrainOptions<'a>) -> Result<Self, MetaError> {
        let config = opts.config;
        let (tasks, meta_tasks) = load_tasks(config, opts.datasets, opts.seed)?;
        create_dir(opts.out_dir)?;
        write_file(&opts.out_dir.join("config.toml"), &config.to_toml_string())?;
        let evaluators = (tasks.iter())
            .map(|t| Evaluator::from_config(config, t))
            .collect();
        Ok(Self {
            opts,
            tasks,
            meta_tasks,
            evaluators,
            csv: None,
        })
    }

    /// Opens `meta_train.csv`, keeping the rows of meta-epochs `1..=kept`.
    fn open_csv(&mut self, kept: usize) -> Result<(), MetaError> {
        let path = self.opts.out_dir.join("meta_train.csv");
        self.csv = Some(open_csv(&path, &self.tasks, kept)?);
        Ok(())
    }

    /// What follows meta-epoch `epoch` of `maml`: every task's evaluation when one is due, the
    /// CSV line, and w0's checkpoint at `checkpoint` (its training state first: the
    /// checkpoint's metadata, written last, marks both complete).
    fn after_epoch(
        &mut self,
        maml: &Maml,
        epoch: MetaEpoch,
        checkpoint: Option<&Path>,
        started: Instant,
    ) -> Result<MetaRow, MetaError> {
        let (config, e) = (self.opts.config, epoch.epoch);
        let evaluation = is_evaluation_epoch(&config.meta, e).then(|| {
            let (meta, seed) = (&config.meta, self.opts.seed);
            evaluation(maml, meta, &self.meta_tasks, &mut self.evaluators, seed, e)
        });
        if let Some(evaluation) = &evaluation {
            let mean = |returns: &[f64]| returns.iter().sum::<f64>() / returns.len() as f64;
            tracing::info!(
                seed = self.opts.seed,
                meta_epoch = e,
                meta_loss = epoch.meta_loss,
                mean_adapted = mean(&evaluation.adapted),
                mean_zero_shot = mean(&evaluation.zero_shot),
                "greedy returns"
            );
        }
        let row = self.log_row(epoch, evaluation, started)?;
        if let Some(path) = checkpoint {
            let algorithm = Method::maml(config.meta.inner_loss).name();
            maml.save_state(path)?;
            checkpoint::save(path, maml.w0(), &algorithm, e, config)?;
        }
        Ok(row)
    }

    /// The row of meta-epoch `epoch`, written to the CSV.
    fn log_row(
        &mut self,
        epoch: MetaEpoch,
        evaluation: Option<Evaluation>,
        started: Instant,
    ) -> Result<MetaRow, MetaError> {
        let row = MetaRow {
            epoch,
            evaluation,
            seconds: started.elapsed().as_secs_f64(),
        };
        let csv = self
            .csv
            .as_mut()
            .expect("open_csv runs before the first meta-epoch");
        csv.line(&csv_line(&row, self.tasks.len()))?;
        Ok(row)
    }
}

/// Every task's greedy returns after meta-epoch `epoch`, adapted and zero-shot.
fn evaluation(
    maml: &Maml,
    meta: &MetaConfig,
    tasks: &[MetaTask],
    evaluators: &mut [Evaluator],
    seed: u64,
    epoch: usize,
) -> Evaluation {
    Evaluation {
        adapted: (tasks.iter().zip(evaluators.iter_mut()).enumerate())
            .map(|(i, (task, evaluator))| {
                let stream = seed ^ ((epoch as u64) << 32) ^ i as u64;
                adapted_return(maml, meta, task, evaluator, stream)
            })
            .collect(),
        zero_shot: (evaluators.iter_mut())
            .map(|evaluator| evaluator.evaluate(maml.w0()).ret.mean)
            .collect(),
    }
}

/// `task`'s greedy return after adaptation (eq. 14 on fresh support shots), averaged over
/// `meta.eval_adaptations` independent adaptations. The shots come from streams of their own,
/// keyed by `stream` (seed, meta-epoch and task), so evaluating leaves training unchanged.
fn adapted_return(
    maml: &Maml,
    meta: &MetaConfig,
    task: &MetaTask,
    evaluator: &mut Evaluator,
    stream: u64,
) -> f64 {
    let adaptations = meta.eval_adaptations;
    let total: f64 = (0..adaptations as u64)
        .map(|a| {
            let mut rng = ChaCha8Rng::seed_from_u64(stream ^ (a << 48));
            let shots = task.sample(meta.support_batch_size, meta.query_batch_size, &mut rng);
            evaluator.evaluate(&maml.adapted(&shots.support)).ret.mean
        })
        .sum();
    total / adaptations as f64
}

/// Whether every task is evaluated after meta-epoch `epoch`: every `meta.eval_every` and after the
/// last.
fn is_evaluation_epoch(meta: &MetaConfig, epoch: usize) -> bool {
    epoch == meta.meta_epochs || (meta.eval_every > 0 && epoch.is_multiple_of(meta.eval_every))
}

/// Whether w0 is checkpointed after meta-epoch `epoch`.
fn is_checkpoint_epoch(meta: &MetaConfig, epoch: usize) -> bool {
    epoch.is_multiple_of(meta.checkpoint_every) || epoch == meta.meta_epochs
}

/// A new MAML from the init of `opts.seed`, or, with `opts.resume`, the one saved with the
/// latest complete checkpoint `hook` names; and the meta-epochs behind it.
fn start_or_resume(
    opts: &MetaTrainOptions,
    hook: &impl MetaTrainHook,
) -> Result<(Maml, usize), MetaError> {
    let config = opts.config;
    let latest = (1..=config.meta.meta_epochs)
        .rev()
        .filter(|&e| opts.resume && is_checkpoint_epoch(&config.meta, e))
        .map(|e| (e, hook.checkpoint_path(e)))
        .find(|(_, path)| checkpoint::read_meta(path).is_ok());
    let maml = MamlConfig::from_config(config);
    match latest {
        None => {
            let w = &config.world;
            let mut w0 = QNetworkConfig::for_world(w, &config.learner.hidden).init(opts.seed);
            algorithm::prepare(&mut w0, config.meta.inner_loss, &config.learner);
            Ok((Maml::new(w0, maml, opts.seed)?, 0))
        }
        Some((epoch, path)) => {
            tracing::info!(epoch, path = %path.display(), "resuming meta-training");
            let w0 = checkpoint::load(&path, config)?.0;
            Ok((Maml::resume(w0, maml, &path)?, epoch))
        }
    }
}

/// `meta_train.csv`: a new log, keeping the rows of meta-epochs `1..=kept` of an existing one:
/// those a resumed run does not repeat.
fn open_csv(path: &Path, tasks: &[TaskConfig], kept: usize) -> Result<CsvLog, MetaError> {
    let mut header = String::from("meta_epoch,meta_loss");
    for t in tasks {
        header.push_str(&format!(",loss_{}", t.name));
    }
    for prefix in ["return", "zero_shot"] {
        for t in tasks {
            header.push_str(&format!(",{prefix}_{}", t.name));
        }
    }
    header.push_str(",seconds");
    let done = |line: &str| {
        let epoch = line.split(',').next().and_then(|c| c.parse::<usize>().ok());
        epoch.is_some_and(|e| e <= kept)
    };
    Ok(CsvLog::resume(path, &header, done)?)
}

/// `row`'s line of `meta_train.csv`, for a run of `tasks` tasks.
fn csv_line(row: &MetaRow, tasks: usize) -> String {
    let mut losses = vec![String::new(); tasks];
    for &(task, loss) in &row.epoch.task_losses {
        losses[task] = loss.to_string();
    }
    let cells = |pick: fn(&Evaluation) -> &Vec<f64>| match &row.evaluation {
        Some(evaluation) => pick(evaluation).iter().map(f64::to_string).collect(),
        None => vec![String::new(); tasks],
    };
    format!(
        "{},{},{},{},{},{:.3}",
        row.epoch.epoch,
        row.epoch.meta_loss,
        losses.join(","),
        cells(|e| &e.adapted).join(","),
        cells(|e| &e.zero_shot).join(","),
        row.seconds
    )
}
