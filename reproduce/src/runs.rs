//! What each seed of a reproduction computes, item by item, and the artefacts it caches under
//! `OUT/cache/seed-S/`: every task's dataset, the online DQN reference agents, the meta-trained
//! w0s, then every fine-tuning run the selected experiments need (each run once, as long as the
//! longest experiment using it asks: a fine-tuning run's first E epochs do not depend on how many
//! epochs follow, so shorter experiments read a prefix).
//!
//! A cached artefact is reused only when the config saved beside it (`collect`'s
//! `FILE.config.toml`, a checkpoint's `P.toml`) is the text of the config that would make it now;
//! anything else is made again, so a changed key can never leave a stale dataset or w0 in use.

use std::path::{Path, PathBuf};

use indicatif::ProgressBar;
use uavmeta_actors::collect::{agent_path, collect, config_path};
use uavmeta_actors::policy::q_policy::{Evaluator, QPolicy};
use uavmeta_learner::checkpoint::{self, CheckpointPaths};
use uavmeta_learner::progress::OnStep;
use uavmeta_learner::qnet::QNetworkConfig;
use uavmeta_learner::train::{EpochRow, EvaluatePolicy};
use uavmeta_learner::transitions::load_shots;
use uavmeta_meta::context;
use uavmeta_meta::fine_tune::{fine_tune, init_network, FineTune};
use uavmeta_meta::meta_train::{
    dataset_path, load_tasks, meta_train, Evaluation, MetaRow, MetaTrainOptions,
};
use uavmeta_meta::{create_dir, pretrain, MetaError};
use uavmeta_proto::config::{Config, TaskConfig, TaskRole};
use uavmeta_proto::dataset::DatasetReader;
use uavmeta_proto::method::{Algo, Method, Start};
use uavmeta_proto::stats::PolicyMetrics;
use uavmeta_world::heuristics::{model_planner_metrics, PolicySpec};
use uavmeta_world::rollout::{record_trajectory, Trajectory};

use crate::{Experiment, ReproduceError};

/// How a trained init is made.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Init {
    /// MAML (Algorithm 4) with this inner loss: w0.
    Maml(Algo),
    /// This algorithm on the union of the meta-train tasks' shots (`uavmeta_meta::pretrain`).
    Pretrain(Algo),
    /// The context learner trained with this algorithm on the meta-train tasks' shots
    /// (`uavmeta_meta::context`); a run starts from its policy for the run's shots.
    Context(Algo),
}

/// The reproduction's w0: CQL-MAML's, which the `-w0` baselines start from too.
pub const W0: Init = Init::Maml(Algo::CQL);

impl Init {
    /// How `method`'s starting network is trained; `None` for a random one.
    pub fn of(method: Method) -> Option<Init> {
        match (method, method.start()) {
            (Method::MetaInit, _) | (_, Some(Start::W0)) => Some(W0),
            (Method::FineTuned { algo, .. }, Some(Start::Maml)) => Some(Init::Maml(algo)),
            (Method::FineTuned { algo, .. }, Some(Start::Pretrain)) => Some(Init::Pretrain(algo)),
            (Method::FineTuned { algo, .. }, Some(Start::Context)) => Some(Init::Context(algo)),
            _ => None,
        }
    }

    /// The algorithm it trains with.
    pub fn algo(self) -> Algo {
        match self {
            Init::Maml(algo) | Init::Pretrain(algo) | Init::Context(algo) => algo,
        }
    }

    /// The name of the checkpoints it makes: the method fine-tuned from it.
    pub fn name(self) -> String {
        match self {
            Init::Maml(algo) => Method::tuned(algo, Start::Maml).name(),
            Init::Pretrain(algo) => Method::tuned(algo, Start::Pretrain).name(),
            Init::Context(algo) => Method::tuned(algo, Start::Context).name(),
        }
    }
}

/// A trained init: how, and on how many meta-train tasks (the first n).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct InitKey {
    pub kind: Init,
    pub tasks: usize,
}

/// One fine-tuning run, whatever its length.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct RunKey {
    pub task: String,
    pub method: Method,
    pub shots: usize,
    /// Meta-train tasks behind the init; 0 for a random init.
    pub meta_tasks: usize,
    pub eval_episodes: usize,
}

impl RunKey {
    pub fn init(&self) -> Option<InitKey> {
        Init::of(self.method).map(|kind| InitKey {
            kind,
            tasks: self.meta_tasks,
        })
    }
}

/// A reference line on a task: the online DQN agent, evaluated over `episodes`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct RefKey {
    pub task: String,
    pub episodes: usize,
}

/// The planner in the world a seed's `shots` shots of `task` fit, evaluated over `episodes`: the
/// model-based section's reference line.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ModelPlannerKey {
    pub task: String,
    pub shots: usize,
    pub episodes: usize,
}

/// What the planner in the fitted world scored, or why the shots fit no world (rain).
pub type ModelPlanned = Result<PolicyMetrics, String>;

/// Something a seed computes, with the experiments that use it (whose progress bars it moves).
#[derive(Debug, Clone)]
pub struct Need<K> {
    pub key: K,
    pub users: Vec<Experiment>,
}

/// A fine-tuning run to do: as many epochs as its longest user asks for.
#[derive(Debug, Clone)]
pub struct RunNeed {
    pub need: Need<RunKey>,
    pub epochs: usize,
    /// Record the final greedy policy's path (figure 9c).
    pub trajectory: bool,
}

impl RunNeed {
    /// The algorithm that fine-tunes it.
    pub fn algo(&self) -> Algo {
        self.need
            .key
            .method
            .algo()
            .expect("every run of the plan is a fine-tuned method")
    }
}

/// Everything every seed computes for the selected experiments, each item once.
#[derive(Debug, Clone, Default)]
pub struct Plan {
    /// Task names, collected in this order.
    pub datasets: Vec<Need<String>>,
    pub references: Vec<Need<RefKey>>,
    pub model_planners: Vec<Need<ModelPlannerKey>>,
    pub inits: Vec<Need<InitKey>>,
    pub runs: Vec<RunNeed>,
}

impl<K> Need<K> {
    fn new(key: K, user: Experiment) -> Self {
        let users = vec![user];
        Self { key, users }
    }

    fn add_user(&mut self, user: Experiment) {
        if !self.users.contains(&user) {
            self.users.push(user);
        }
    }
}

/// `key` in `needs`, used by `user`.
fn add<K: PartialEq>(needs: &mut Vec<Need<K>>, key: K, user: Experiment) {
    match needs.iter_mut().find(|n| n.key == key) {
        Some(need) => need.add_user(user),
        None => needs.push(Need::new(key, user)),
    }
}

impl Plan {
    pub fn dataset(&mut self, task: &str, user: Experiment) {
        add(&mut self.datasets, task.to_string(), user);
    }

    /// A meta-trained w0 and the datasets of its tasks.
    pub fn init(&mut self, config: &Config, key: InitKey, user: Experiment) {
        for task in meta_train_tasks(config, key.tasks) {
            self.dataset(&task.name, user);
        }
        add(&mut self.inits, key, user);
    }

    pub fn reference(&mut self, task: &str, episodes: usize, user: Experiment) {
        self.dataset(task, user);
        let key = RefKey {
            task: task.to_string(),
            episodes,
        };
        add(&mut self.references, key, user);
    }

    /// The planner in the world the shots of `key` fit: wherever a model-based method runs.
    pub fn model_planner(&mut self, key: ModelPlannerKey, user: Experiment) {
        self.dataset(&key.task, user);
        add(&mut self.model_planners, key, user);
    }

    pub fn run(
        &mut self,
        config: &Config,
        key: RunKey,
        epochs: usize,
        trajectory: bool,
        user: Experiment,
    ) {
        self.dataset(&key.task, user);
        if let Some(init) = key.init() {
            self.init(config, init, user);
        }
        match self.runs.iter_mut().find(|r| r.need.key == key) {
            Some(run) => {
                run.epochs = run.epochs.max(epochs);
                run.trajectory |= trajectory;
                run.need.add_user(user);
            }
            None => self.runs.push(RunNeed {
                need: Need::new(key, user),
                epochs,
                trajectory,
            }),
        }
    }

    /// Units of work of `experiment` in one seed, the length of its progress bar per seed.
    pub fn units(&self, experiment: Experiment) -> u64 {
        let uses = |users: &[Experiment]| users.contains(&experiment) as u64;
        self.datasets.iter().map(|n| uses(&n.users)).sum::<u64>()
            + self.references.iter().map(|n| uses(&n.users)).sum::<u64>()
            + self
                .model_planners
                .iter()
                .map(|n| uses(&n.users))
                .sum::<u64>()
            + self.inits.iter().map(|n| uses(&n.users)).sum::<u64>()
            + self.runs.iter().map(|r| uses(&r.need.users)).sum::<u64>()
    }
}

/// The first `n` meta-train tasks in config order.
pub fn meta_train_tasks(config: &Config, n: usize) -> impl Iterator<Item = &TaskConfig> {
    config.tasks_with_role(TaskRole::MetaTrain).take(n)
}

/// The meta-train curve of a w0 (figure 4): meta-loss per meta-epoch, and per evaluated
/// meta-epoch each task's greedy return after adaptation and zero-shot.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct MetaCurve {
    pub meta_loss: Vec<f64>,
    pub evaluations: Vec<(usize, Evaluation)>,
}

impl MetaCurve {
    /// The curve of a meta-training's rows.
    pub fn of(rows: &[MetaRow]) -> Self {
        Self {
            meta_loss: rows.iter().map(|r| r.epoch.meta_loss).collect(),
            evaluations: (rows.iter())
                .filter_map(|r| r.evaluation.clone().map(|ev| (r.epoch.epoch, ev)))
                .collect(),
        }
    }
}

/// A finished fine-tuning run, as the cache writes it.
#[derive(Debug, Clone, serde::Serialize, serde::Deserialize)]
pub struct RunResult {
    pub rows: Vec<EpochRow>,
    pub trajectory: Option<Trajectory>,
}

/// What one seed measured.
#[derive(Debug, Clone)]
pub struct SeedResult {
    pub seed: u64,
    pub inits: Vec<(InitKey, MetaCurve)>,
    /// The online DQN agent of each reference task.
    pub references: Vec<(RefKey, PolicyMetrics)>,
    pub model_planners: Vec<(ModelPlannerKey, ModelPlanned)>,
    pub runs: Vec<(RunKey, RunResult)>,
}

impl SeedResult {
    pub fn run(&self, key: &RunKey) -> &RunResult {
        lookup(&self.runs, |k| k == key, "run")
    }

    pub fn reference(&self, task: &str, episodes: usize) -> &PolicyMetrics {
        let of = |k: &RefKey| k.task == task && k.episodes == episodes;
        lookup(&self.references, of, "reference")
    }

    pub fn model_planner(&self, key: &ModelPlannerKey) -> &ModelPlanned {
        lookup(&self.model_planners, |k| k == key, "model planner")
    }

    pub fn meta_curve(&self, key: InitKey) -> &MetaCurve {
        lookup(&self.inits, |k| *k == key, "init")
    }
}

/// The value of the first key `of` picks; `what` names the item in the panic when none does.
fn lookup<'a, K, V>(pairs: &'a [(K, V)], of: impl Fn(&K) -> bool, what: &str) -> &'a V {
    let found = pairs.iter().find(|(k, _)| of(k)).map(|(_, v)| v);
    found.unwrap_or_else(|| panic!("every {what} an experiment reads is in the plan it built"))
}

/// The config that collects seed `seed`'s datasets and trains its online DQN agents: the
/// sections a dataset depends on (`[world]`, `[[tasks]]`, `[collect]` with its seed offset by
/// `seed`, `[learner]`) and every other section at its defaults.
fn collection_config(config: &Config, seed: u64) -> Config {
    let mut c = Config {
        world: config.world.clone(),
        tasks: config.tasks.clone(),
        collect: config.collect.clone(),
        learner: config.learner.clone(),
        origin: config.origin.clone(),
        ..Config::default()
    };
    c.collect.seed = config.collect.seed + seed;
    c
}

/// The config of one meta-training: the run's `[meta]` and `[context]`, with its tasks cut to the
/// first `key.tasks` meta-train tasks, the inner loss of `key`, figure 4's evaluation interval `eval_every`
/// (evaluating does not change training, so every w0 shares it and one w0 serves every figure)
/// and no `[reproduce]`, which meta-training does not read.
fn meta_config(config: &Config, key: InitKey, seed: u64, eval_every: usize) -> Config {
    let mut c = collection_config(config, seed);
    c.meta = config.meta.clone();
    c.context = config.context.clone();
    c.meta.inner_loss = key.kind.algo();
    c.meta.eval_every = eval_every;
    c.tasks = meta_train_tasks(config, key.tasks).cloned().collect();
    c
}

/// Whether the config saved beside a dataset at `path` agrees with `collection` on every section a
/// dataset depends on. Comparing values rather than text keeps the cache when another section
/// changes or any section gains a key at its default.
fn saved_collection_matches(path: &Path, collection: &Config) -> bool {
    Config::load(path, &[]).is_ok_and(|saved| {
        saved.world == collection.world
            && saved.tasks == collection.tasks
            && saved.collect == collection.collect
            && saved.learner == collection.learner
    })
}

/// Whether the config saved at `path` has `config`'s values, its origin aside. `[reproduce]` is
/// left out of the comparison too: no init reads it, and configs saved before the section moved
/// to this crate wrote it out in full. As in [`saved_collection_matches`], comparing values keeps
/// the cache when a section gains a key at its default.
fn saved_config_matches(path: &Path, config: &Config) -> bool {
    Config::load(path, &[]).is_ok_and(|saved| {
        let saved = Config {
            origin: config.origin.clone(),
            reproduce: config.reproduce.clone(),
            ..saved
        };
        saved == *config
    })
}

/// Where seed `seed` caches its artefacts.
pub fn seed_dir(out: &Path, seed: u64) -> PathBuf {
    out.join("cache").join(format!("seed-{seed}"))
}

/// Where seed `seed` keeps its datasets and, beside each, the online DQN agent that made it.
fn datasets_dir(out: &Path, seed: u64) -> PathBuf {
    seed_dir(out, seed).join("datasets")
}

/// One dataset the plan needs: seed `seed`'s of task `task`.
pub struct DatasetJob {
    task: String,
    collection: Config,
    path: PathBuf,
}

impl DatasetJob {
    /// Seed `seed`'s dataset of `task`, with the config that collects it.
    pub fn new(config: &Config, out: &Path, seed: u64, task: &str) -> Result<Self, ReproduceError> {
        let datasets = datasets_dir(out, seed);
        create_dir(&datasets)?;
        Ok(Self {
            task: task.to_string(),
            collection: collection_config(config, seed),
            path: dataset_path(&datasets, task),
        })
    }

    /// Whether the file is complete and was collected with the same world, tasks, collection
    /// and learner (the online DQN agent, the reference line, saved beside it).
    pub fn cached(&self) -> bool {
        dataset_cached(&self.collection, &self.path)
    }
}

/// Collects `job` (not cached) as `uavmeta collect` does.
pub fn collect_dataset(job: &DatasetJob) -> Result<(), ReproduceError> {
    let progress = ProgressBar::hidden();
    collect(&job.collection, &job.task, &job.path, &progress)?;
    Ok(())
}

/// The online DQN agent behind seed `seed`'s dataset of a task (saved by `collect`), evaluated.
pub fn reference(
    config: &Config,
    out: &Path,
    seed: u64,
    key: &RefKey,
) -> Result<PolicyMetrics, ReproduceError> {
    let task = config.task(&key.task).map_err(MetaError::from)?;
    let agent = agent_path(&dataset_path(&datasets_dir(out, seed), &task.name));
    let (agent, _) =
        checkpoint::load(&agent, &collection_config(config, seed)).map_err(MetaError::from)?;
    let metrics = Evaluator::new(&config.world, task, key.episodes, config.learner.eval_seed)
        .evaluate(&agent);
    tracing::info!(seed, task = %task.name, ret = %metrics.ret, aoi = %metrics.aoi, power_mw = %metrics.power_mw, "online DQN reference");
    Ok(metrics)
}

/// Seed `seed`'s init of `key`, trained into `SEED_DIR/<cql-maml|dqn-maml|cql-pretrain|..>-tasks-N/`
/// unless that directory holds one made with the same config: its checkpoint and meta-train curve
/// (empty for a pretrained init), with the adapted policies evaluated every `eval_every`
/// meta-epochs (`reproduce.meta_eval_every`).
pub fn init(
    config: &Config,
    out: &Path,
    seed: u64,
    key: InitKey,
    eval_every: usize,
) -> Result<(PathBuf, MetaCurve), ReproduceError> {
    let meta = meta_config(config, key, seed, eval_every);
    let datasets = &datasets_dir(out, seed);
    let w0 = w0_path(out, seed, key);
    let out = w0.parent().expect("w0 is a file of its init's directory");
    if let Init::Pretrain(_) | Init::Context(_) = key.kind {
        let paths = CheckpointPaths::new(&w0);
        let saved = saved_config_matches(&paths.config, &meta)
            && checkpoint::read_meta(&w0).is_ok_and(|m| m.epoch == meta.meta.meta_epochs);
        if !saved {
            remove_checkpoint(&w0)?;
            multi_task_init(&meta, datasets, seed, key.kind, &w0)?;
        }
        return Ok((w0, MetaCurve::default()));
    }
    if let Some(cached) = cached_w0(&meta, key, out) {
        return Ok(cached);
    }
    remove_checkpoint(&w0)?;
    let result = meta_train(&MetaTrainOptions {
        config: &meta,
        datasets,
        out_dir: out,
        seed,
        progress: false,
        resume: false,
        on_step: OnStep::default(),
    })?;
    Ok((result.w0, MetaCurve::of(&result.rows)))
}

/// Removes the checkpoint `path` an earlier config left, its config first: a checkpoint's files
/// are saved config, weights, then metadata, so a kill while the new one is saved must not find
/// the old metadata and weights beside the new config.
fn remove_checkpoint(path: &Path) -> Result<(), ReproduceError> {
    let paths = CheckpointPaths::new(path);
    for file in [&paths.config, &paths.meta, &paths.weights] {
        match std::fs::remove_file(file) {
            Err(e) if e.kind() != std::io::ErrorKind::NotFound => {
                let error = uavmeta_proto::fs::FileError::at(file, "remove")(e);
                return Err(MetaError::from(error).into());
            }
            _ => {}
        }
    }
    Ok(())
}

/// Where seed `seed`'s init of `key` is saved: `SEED_DIR/<cql-maml|dqn-maml|..>-tasks-N/w0`.
pub fn w0_path(out: &Path, seed: u64, key: InitKey) -> PathBuf {
    let dir = format!("{}-tasks-{}", key.kind.name(), key.tasks);
    seed_dir(out, seed).join(dir).join("w0")
}

/// The meta-train curve of seed `seed`'s init of `key`, made by [`init`] (empty for a pretrained
/// or context init); an error when the cache holds no complete one.
pub fn init_curve(
    config: &Config,
    out: &Path,
    seed: u64,
    key: InitKey,
    eval_every: usize,
) -> Result<MetaCurve, ReproduceError> {
    if let Init::Pretrain(_) | Init::Context(_) = key.kind {
        return Ok(MetaCurve::default());
    }
    let meta = meta_config(config, key, seed, eval_every);
    let w0 = w0_path(out, seed, key);
    let dir = w0.parent().expect("w0 is a file of its init's directory");
    match cached_w0(&meta, key, dir) {
        Some((_, curve)) => Ok(curve),
        None => Err(ReproduceError::Cache {
            path: dir.join("meta_train.csv"),
            message: "no complete meta-training of this config".into(),
        }),
    }
}

/// Trains the pretrained or context init `kind` on `meta`'s tasks and saves it as `path`.
fn multi_task_init(
    meta: &Config,
    datasets: &Path,
    seed: u64,
    kind: Init,
    path: &Path,
) -> Result<(), ReproduceError> {
    let (_, tasks) = load_tasks(meta, datasets, seed)?;
    let always = |_| Ok::<_, ReproduceError>(true);
    let finished = "a training never told to stop finishes";
    match kind {
        Init::Context(_) => context::meta_train(meta, &tasks, seed, OnStep::default(), always)?
            .expect(finished)
            .save(path, meta),
        _ => {
            let q =
                pretrain::pretrain(meta, &tasks, seed, OnStep::default(), always)?.expect(finished);
            checkpoint::save(path, &q, &kind.name(), meta.meta.meta_epochs, meta).map(|_| ())
        }
    }
    .map_err(MetaError::from)?;
    Ok(())
}

/// Seed `seed`'s model planner `key`: on the shots its fine-tuning runs of the same task and
/// shot count read.
pub fn model_planner(
    config: &Config,
    out: &Path,
    seed: u64,
    key: &ModelPlannerKey,
) -> Result<ModelPlanned, ReproduceError> {
    let task = config.task(&key.task).map_err(MetaError::from)?;
    let dataset = dataset_path(&datasets_dir(out, seed), &task.name);
    let shots = load_shots(config, task, &dataset, key.shots, seed).map_err(MetaError::from)?;
    let planned = model_planner_metrics(config, task, &shots.rows, key.episodes);
    let planned = planned.map_err(|why| why.to_string());
    match &planned {
        Ok(m) => {
            tracing::info!(seed, task = %task.name, shots = key.shots, ret = %m.ret, "model planner")
        }
        Err(why) => {
            tracing::info!(seed, task = %task.name, shots = key.shots, %why, "no model planner")
        }
    }
    Ok(planned)
}

/// Seed `seed`'s fine-tuning run `run`, from the checkpoint `w0` (its init, `None` for a random
/// one), evaluated after every epoch.
pub fn fine_tune_run(
    config: &Config,
    out: &Path,
    seed: u64,
    run: &RunNeed,
    w0: Option<&Path>,
) -> Result<RunResult, ReproduceError> {
    let key = &run.need.key;
    let task = config.task(&key.task).map_err(MetaError::from)?;
    let dataset = dataset_path(&datasets_dir(out, seed), &task.name);
    let shots = load_shots(config, task, &dataset, key.shots, seed).map_err(MetaError::from)?;
    let mut q = match w0 {
        Some(w0) => init_network(w0, config, &shots.data)?.0,
        None => QNetworkConfig::for_world(&config.world, &config.learner.hidden).init(seed),
    };
    let mut eval_config = config.clone();
    eval_config.learner.eval_episodes = key.eval_episodes;
    let settings = FineTune {
        config: &eval_config,
        task,
        epochs: run.epochs,
        seed,
        out_dir: None,
        progress: false,
        on_step: OnStep::default(),
    };
    let mut evaluator = Evaluator::from_config(&eval_config, task).with_model(&shots.rows);
    let rows = fine_tune(&mut q, &shots.data, run.algo(), &settings, &mut evaluator)?;
    // The final greedy policy's path, when the plan asks for it.
    let trajectory = run.trajectory.then(|| {
        let mut policy = QPolicy::new(&q);
        record_trajectory(&config.world, task, &mut policy, config.learner.eval_seed)
    });
    if let Some(last) = rows.last() {
        tracing::info!(seed, task = %task.name, method = key.method.name(), shots = key.shots, meta_tasks = key.meta_tasks, epochs = run.epochs, ret = %last.policy.ret, "fine-tuned");
    }
    Ok(RunResult { rows, trajectory })
}

/// Whether the dataset at `path` is complete and was collected with `collection`'s world, tasks,
/// collection and learner.
fn dataset_cached(collection: &Config, path: &Path) -> bool {
    if !saved_collection_matches(&config_path(path), collection) {
        return false;
    }
    let complete = DatasetReader::open(path).is_ok_and(|reader| {
        reader.check_world(collection).is_ok()
            && reader.transitions().len() == collection.collect.transitions
    });
    // The online DQN agent, the reference line, is saved last.
    complete
        && (collection.collect.policy != PolicySpec::DqnOnline.to_string()
            || checkpoint::read_meta(&agent_path(path)).is_ok())
}

/// The meta-trained w0 in `out` and its curve, if `out` holds one made with `meta` and its whole
/// `meta_train.csv`.
fn cached_w0(meta: &Config, key: InitKey, out: &Path) -> Option<(PathBuf, MetaCurve)> {
    let w0 = out.join("w0");
    if !saved_config_matches(&CheckpointPaths::new(&w0).config, meta) {
        return None;
    }
    // `w0` is saved once, after the last meta-epoch's CSV row (the checkpoints before it are
    // `w0-eNNNN`), its metadata last: that metadata marks the whole run complete, whatever a
    // kill left of the CSV's last line.
    let last = checkpoint::read_meta(&w0).is_ok_and(|m| m.epoch == meta.meta.meta_epochs);
    if !last {
        return None;
    }
    let csv = out.join("meta_train.csv");
    match std::fs::read_to_string(&csv)
        .ok()
        .and_then(|text| parse_meta_csv(&text, key.tasks))
    {
        Some(curve) if curve.meta_loss.len() == meta.meta.meta_epochs => Some((w0, curve)),
        _ => {
            tracing::warn!(csv = %csv.display(), "unreadable or incomplete; meta-training again");
            None
        }
    }
}

/// Reads back `meta_train.csv` of `tasks` tasks (columns: meta_epoch, meta_loss, one loss, then
/// one adapted and then one zero-shot return per task, seconds; empty returns on meta-epochs that
/// were not evaluated).
fn parse_meta_csv(text: &str, tasks: usize) -> Option<MetaCurve> {
    let mut curve = MetaCurve::default();
    for line in text.lines().skip(1) {
        let cells: Vec<&str> = line.split(',').collect();
        if cells.len() != 3 + 3 * tasks {
            return None;
        }
        let epoch: usize = cells[0].parse().ok()?;
        curve.meta_loss.push(cells[1].parse().ok()?);
        let returns = &cells[2 + tasks..2 + 3 * tasks];
        if returns.iter().all(|c| !c.is_empty()) {
            let mut parsed = returns
                .iter()
                .map(|c| c.parse().ok())
                .collect::<Option<Vec<f64>>>()?;
            let zero_shot = parsed.split_off(tasks);
            let evaluation = Evaluation {
                adapted: parsed,
                zero_shot,
            };
            curve.evaluations.push((epoch, evaluation));
        }
    }
    Some(curve)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn meta_csv_reads_back_losses_and_evaluated_returns() {
        let text = "meta_epoch,meta_loss,loss_a,loss_b,return_a,return_b,zero_shot_a,zero_shot_b,seconds\n\
                    1,2.5,1,1.5,,,,,0.1\n\
                    2,2.0,0.9,1.1,-800,-900.5,-850,-700,0.2\n";
        let curve = parse_meta_csv(text, 2).unwrap();
        assert_eq!(curve.meta_loss, vec![2.5, 2.0]);
        let evaluation = Evaluation {
            adapted: vec![-800.0, -900.5],
            zero_shot: vec![-850.0, -700.0],
        };
        assert_eq!(curve.evaluations, vec![(2, evaluation)]);
        // A file of another task count is not this w0's.
        assert!(parse_meta_csv(text, 3).is_none());
    }

    #[test]
    fn a_run_needed_twice_is_planned_once_at_its_longest() {
        let config = Config::default();
        let key = RunKey {
            task: "lambda-300".into(),
            method: Method::CQL_MAML,
            shots: 500,
            meta_tasks: 8,
            eval_episodes: 20,
        };
        let mut plan = Plan::default();
        plan.run(&config, key.clone(), 100, false, Experiment::Convergence);
        plan.run(&config, key.clone(), 50, false, Experiment::AoiPower);
        plan.run(
            &config,
            RunKey {
                method: Method::CQL,
                meta_tasks: 0,
                ..key
            },
            40,
            false,
            Experiment::AoiPower,
        );
        assert_eq!(plan.runs.len(), 2);
        assert_eq!(plan.runs[0].epochs, 100);
        assert_eq!(
            plan.runs[0].need.users,
            vec![Experiment::Convergence, Experiment::AoiPower]
        );
        // The init of the CQL-MAML run and the datasets of its eight tasks plus the unseen one.
        assert_eq!(plan.inits.len(), 1);
        assert_eq!(plan.datasets.len(), 9);
        assert_eq!(plan.units(Experiment::AoiPower), 9 + 1 + 2);
        assert_eq!(plan.units(Experiment::Convergence), 9 + 1 + 1);
    }

    #[test]
    fn a_cached_init_serves_whatever_its_saved_config_wrote_of_reproduce() {
        let dir = std::env::temp_dir().join(format!("uavmeta-saved-config-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("w0.toml");
        let mut run = Config::default();
        crate::ReproduceConfig::default().write_into(&mut run);
        let key = InitKey { kind: W0, tasks: 8 };
        let meta = meta_config(&run, key, 1, 10);
        assert!(meta.reproduce.is_empty());
        // Saved before `[reproduce]` moved to this crate: every key written out.
        let written_out = Config {
            reproduce: run.reproduce.clone(),
            ..meta.clone()
        };
        std::fs::write(&path, written_out.to_toml_string()).unwrap();
        assert!(saved_config_matches(&path, &meta));
        std::fs::write(&path, meta.to_toml_string()).unwrap();
        assert!(saved_config_matches(&path, &meta));
        // Any section meta-training reads still decides.
        let mut other = meta.clone();
        other.meta.eval_every = 5;
        assert!(!saved_config_matches(&path, &other));
        other = meta.clone();
        other.learner.alpha = 10.0;
        assert!(!saved_config_matches(&path, &other));
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
