//! The reproduction's plan as a graph of jobs over the shared cache, `OUT/plan.json`, and the one
//! function that runs a job, whichever engine calls it: the local pool ([`run_local`]) or Slurm
//! (`crate::slurm`, one array of jobs per [`Kind`]).
//!
//! Every job reads its inputs from the cache under `OUT/cache/` and writes its outputs there
//! (`crate::cache`); a job is done when its marker holds its stamp (the config's fingerprint and
//! its parameters), and a done job is a no-op. Jobs of a kind depend only on jobs of the kinds
//! before it ([`Kind::after`]), so the stages of the graph are its kinds, in [`Kind::ALL`]'s
//! order. The figures job reads only the cache; it always draws again (it is cheap, and the
//! figures' code is not part of the stamp).

use std::path::{Path, PathBuf};
use std::time::{Duration, SystemTime};

use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use uavmeta_meta::MetaError;
use uavmeta_proto::config::Config;
use uavmeta_proto::fs::FileError;
use uavmeta_world::heuristics::reference_metrics;

use crate::cache;
use crate::runs::{
    self, meta_train_tasks, InitKey, ModelPlannerKey, Plan, RefKey, RunNeed, SeedResult,
};
use crate::{Experiment, HeuristicRef, ReproduceConfig, ReproduceError, ReproduceOptions};

/// What a job makes.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Kind {
    /// A seed's dataset of a task and the online DQN agent that made it.
    Dataset,
    /// The seed-free reference rows of a task: random, the heuristics, the planner.
    Heuristics,
    /// A seed's online DQN agent of a task, evaluated.
    Reference,
    /// The planner in the world a seed's shots of a task fit: the model-based section's
    /// reference.
    ModelPlanner,
    /// A seed's trained init: w0 by MAML, a pretrained network or a context learner.
    Init,
    /// A seed's fine-tuning run, its epoch rows and path.
    Run,
    /// Every experiment's CSVs, PNGs and summaries, from the cache alone.
    Figures,
}

impl Kind {
    /// In the order the engines run them.
    pub const ALL: [Kind; 7] = [
        Kind::Dataset,
        Kind::Heuristics,
        Kind::Reference,
        Kind::ModelPlanner,
        Kind::Init,
        Kind::Run,
        Kind::Figures,
    ];

    pub fn name(self) -> &'static str {
        match self {
            Kind::Dataset => "dataset",
            Kind::Heuristics => "heuristics",
            Kind::Reference => "reference",
            Kind::ModelPlanner => "model-planner",
            Kind::Init => "init",
            Kind::Run => "run",
            Kind::Figures => "figures",
        }
    }

    pub fn parse(name: &str) -> Option<Kind> {
        Self::ALL.into_iter().find(|k| k.name() == name)
    }

    /// The kinds a job of this kind may wait on.
    pub fn after(self) -> &'static [Kind] {
        match self {
            Kind::Dataset | Kind::Heuristics => &[],
            Kind::Reference | Kind::ModelPlanner | Kind::Init => &[Kind::Dataset],
            Kind::Run => &[Kind::Dataset, Kind::Init],
            // Every kind before it.
            Kind::Figures => &Kind::ALL[..Kind::ALL.len() - 1],
        }
    }
}

/// One job as `plan.json` lists it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct JobSpec {
    pub id: String,
    pub kind: Kind,
    pub seed: Option<u64>,
    /// What it makes, in words: a task, an init, a run's method, shots and tasks.
    pub key: String,
    /// The ids of the jobs it reads the outputs of.
    pub after: Vec<String>,
    /// What its marker holds once it is done.
    pub stamp: String,
}

/// `OUT/plan.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PlanFile {
    /// The fingerprint of the config every job runs with (`[reproduce.slurm]` aside).
    pub config: String,
    pub experiments: Vec<String>,
    pub jobs: Vec<JobSpec>,
}

impl PlanFile {
    pub fn path(out: &Path) -> PathBuf {
        out.join("plan.json")
    }

    /// The plan written in `out`.
    pub fn read(out: &Path) -> Result<Self, ReproduceError> {
        let path = Self::path(out);
        let text = std::fs::read_to_string(&path)
            .map_err(FileError::at(&path, "read"))
            .map_err(MetaError::from)?;
        serde_json::from_str(&text).map_err(|e| ReproduceError::Cache {
            path,
            message: e.to_string(),
        })
    }

    /// The jobs of `kind`, in plan order: a Slurm array's index is the position in this list.
    pub fn of(&self, kind: Kind) -> impl Iterator<Item = &JobSpec> {
        self.jobs.iter().filter(move |j| j.kind == kind)
    }

    /// Whether `job` is done in `out`.
    pub fn done(out: &Path, job: &JobSpec) -> bool {
        cache::is_done(out, &job.id, &job.stamp)
    }
}

/// What a job does, with the plan's items it reads.
#[derive(Debug, Clone, Copy)]
enum Work<'p> {
    Dataset {
        seed: u64,
        task: &'p str,
    },
    Heuristics(&'p RefKey),
    Reference {
        seed: u64,
        key: &'p RefKey,
    },
    ModelPlanner {
        seed: u64,
        key: &'p ModelPlannerKey,
    },
    Init {
        seed: u64,
        key: InitKey,
        eval_every: usize,
    },
    Run {
        seed: u64,
        run: &'p RunNeed,
    },
    Figures,
}

/// A job of the graph: its spec, the experiments it serves (whose progress it moves) and its
/// work.
#[derive(Debug, Clone)]
pub struct Job<'p> {
    pub spec: JobSpec,
    pub users: Vec<Experiment>,
    work: Work<'p>,
}

/// The plan's jobs for every seed, built the same way from the same config and experiments.
pub struct Graph<'p> {
    pub file: PlanFile,
    jobs: Vec<Job<'p>>,
}

/// The fingerprint of the config jobs run with: its text with `[reproduce]` written out in full,
/// where the submission settings (`[reproduce.slurm]`) are at their defaults, since they change
/// where jobs run, not what they make.
pub fn fingerprint(config: &Config, r: &ReproduceConfig) -> String {
    let mut c = config.clone();
    let r = ReproduceConfig {
        slurm: Default::default(),
        ..r.clone()
    };
    r.write_into(&mut c);
    format!("{:08x}", crc32fast::hash(c.to_toml_string().as_bytes()))
}

impl<'p> Graph<'p> {
    /// The graph of `plan` over seeds `0..r.seeds`, for `experiments`.
    pub fn new(
        config: &Config,
        r: &ReproduceConfig,
        plan: &'p Plan,
        experiments: &[Experiment],
    ) -> Self {
        let mut b = Builder {
            fingerprint: fingerprint(config, r),
            meta_eval_every: r.meta_eval_every,
            jobs: Vec::new(),
        };
        for need in &plan.references {
            let key = &need.key;
            let id = format!("heuristics/{}.episodes-{}", key.task, key.episodes);
            b.add(id, None, Work::Heuristics(key), &need.users, vec![], "");
        }
        for seed in 0..r.seeds as u64 {
            b.seed(config, plan, seed);
        }
        let names: Vec<String> = experiments.iter().map(|e| e.name().to_string()).collect();
        let after = b.jobs.iter().map(|j| j.spec.id.clone()).collect();
        let users = experiments.to_vec();
        let params = format!("experiments {}", names.join(","));
        b.add(
            "figures".into(),
            None,
            Work::Figures,
            &users,
            after,
            &params,
        );
        let file = PlanFile {
            config: b.fingerprint,
            experiments: names,
            jobs: b.jobs.iter().map(|j| j.spec.clone()).collect(),
        };
        Self { file, jobs: b.jobs }
    }

    /// The jobs of `kind`, in plan order.
    pub fn of(&self, kind: Kind) -> impl Iterator<Item = &Job<'p>> {
        self.jobs.iter().filter(move |j| j.spec.kind == kind)
    }

    /// The job with id `id`, or the `index`-th of a kind.
    pub fn find(&self, selector: &JobSelector) -> Result<&Job<'p>, ReproduceError> {
        let found = match selector {
            JobSelector::Id(id) => self.jobs.iter().find(|j| j.spec.id == *id),
            JobSelector::Index(kind, index) => self.of(*kind).nth(*index),
        };
        found.ok_or_else(|| ReproduceError::NoSuchJob {
            job: selector.to_string(),
        })
    }

    /// Writes `OUT/plan.json`, unless it already holds this plan (so its time stays the plan's
    /// first).
    pub fn write(&self, out: &Path) -> Result<(), ReproduceError> {
        if PlanFile::read(out).is_ok_and(|written| written == self.file) {
            return Ok(());
        }
        let text = serde_json::to_string_pretty(&self.file).expect("a plan always serialises");
        cache::write(&PlanFile::path(out), &(text + "\n"))
    }

    /// Refuses to run a job of a plan other than the one `OUT/plan.json` holds (an array's index
    /// means a job only in the plan it was submitted with); writes this plan where there is none.
    pub fn check_written(&self, out: &Path) -> Result<(), ReproduceError> {
        if !PlanFile::path(out).exists() {
            return self.write(out);
        }
        match PlanFile::read(out)? == self.file {
            true => Ok(()),
            false => Err(ReproduceError::OtherPlan {
                path: PlanFile::path(out),
            }),
        }
    }
}

/// Which job `--job` or `--stage` with `--index` names.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum JobSelector {
    Id(String),
    Index(Kind, usize),
}

impl std::fmt::Display for JobSelector {
    fn fmt(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
        match self {
            JobSelector::Id(id) => write!(f, "`{id}`"),
            JobSelector::Index(kind, i) => write!(f, "{} job {i}", kind.name()),
        }
    }
}

struct Builder<'p> {
    fingerprint: String,
    meta_eval_every: usize,
    jobs: Vec<Job<'p>>,
}

impl<'p> Builder<'p> {
    fn add(
        &mut self,
        id: String,
        seed: Option<u64>,
        work: Work<'p>,
        users: &[Experiment],
        after: Vec<String>,
        params: &str,
    ) {
        let stamp = format!("config {}; {}\n", self.fingerprint, params);
        // The id is `kind[/seed-S]/key`.
        let rest = id.split_once('/').map_or("", |(_, rest)| rest);
        let key = match seed {
            Some(s) => rest.strip_prefix(&format!("seed-{s}/")).unwrap_or(rest),
            None => rest,
        };
        let spec = JobSpec {
            key: key.to_string(),
            kind: work.kind(),
            id,
            seed,
            after,
            stamp,
        };
        let users = users.to_vec();
        self.jobs.push(Job { spec, users, work });
    }

    /// Seed `seed`'s datasets, references, inits and runs.
    fn seed(&mut self, config: &Config, plan: &'p Plan, seed: u64) {
        let dataset = |task: &str| format!("dataset/seed-{seed}/{task}");
        for need in &plan.datasets {
            let work = Work::Dataset {
                seed,
                task: &need.key,
            };
            self.add(
                dataset(&need.key),
                Some(seed),
                work,
                &need.users,
                vec![],
                "",
            );
        }
        for need in &plan.references {
            let key = &need.key;
            let id = format!(
                "reference/seed-{seed}/{}.episodes-{}",
                key.task, key.episodes
            );
            let work = Work::Reference { seed, key };
            let after = vec![dataset(&key.task)];
            self.add(id, Some(seed), work, &need.users, after, "");
        }
        for need in &plan.model_planners {
            let key = &need.key;
            let id = format!(
                "model-planner/seed-{seed}/{}.shots-{}.episodes-{}",
                key.task, key.shots, key.episodes
            );
            let work = Work::ModelPlanner { seed, key };
            let after = vec![dataset(&key.task)];
            self.add(id, Some(seed), work, &need.users, after, "");
        }
        for need in &plan.inits {
            let key = need.key;
            // Only figure 4 draws a meta-training curve; every other init is evaluated once, at
            // its last meta-epoch (evaluating never changes w0, meta_train.rs).
            let eval_every = match need.users.contains(&Experiment::MetaTraining) {
                true => self.meta_eval_every,
                false => 0,
            };
            let after = meta_train_tasks(config, key.tasks)
                .map(|t| dataset(&t.name))
                .collect();
            let work = Work::Init {
                seed,
                key,
                eval_every,
            };
            let params = format!("evaluated every {eval_every} meta-epochs");
            self.add(
                init_id(seed, key),
                Some(seed),
                work,
                &need.users,
                after,
                &params,
            );
        }
        for run in &plan.runs {
            let key = &run.need.key;
            let mut after = vec![dataset(&key.task)];
            after.extend(key.init().map(|init| init_id(seed, init)));
            let id = format!(
                "run/seed-{seed}/{}/{}.shots-{}.tasks-{}.episodes-{}",
                key.task,
                key.method.name(),
                key.shots,
                key.meta_tasks,
                key.eval_episodes
            );
            let params = format!("{} epochs, path {}", run.epochs, run.trajectory);
            let work = Work::Run { seed, run };
            self.add(id, Some(seed), work, &run.need.users, after, &params);
        }
    }
}

fn init_id(seed: u64, key: InitKey) -> String {
    format!("init/seed-{seed}/{}-tasks-{}", key.kind.name(), key.tasks)
}

impl Work<'_> {
    fn kind(&self) -> Kind {
        match self {
            Work::Dataset { .. } => Kind::Dataset,
            Work::Heuristics(_) => Kind::Heuristics,
            Work::Reference { .. } => Kind::Reference,
            Work::ModelPlanner { .. } => Kind::ModelPlanner,
            Work::Init { .. } => Kind::Init,
            Work::Run { .. } => Kind::Run,
            Work::Figures => Kind::Figures,
        }
    }
}

/// What every job reads: the reproduction's options, its checked `[reproduce]` and its plan.
pub struct JobContext<'a> {
    pub opts: &'a ReproduceOptions<'a>,
    pub r: &'a ReproduceConfig,
    pub plan: &'a Plan,
}

/// Runs `job` unless it is done; the figures job always runs, once every job before it is done.
/// `wall` is the time the reproduction has taken so far, for the summaries.
pub fn run_job(
    ctx: &JobContext,
    job: &Job,
    wall: impl Fn() -> Duration,
) -> Result<Option<crate::ReproduceReport>, ReproduceError> {
    let (config, out) = (ctx.opts.config, ctx.opts.out_dir);
    let spec = &job.spec;
    if spec.kind != Kind::Figures && PlanFile::done(out, spec) {
        tracing::debug!(job = %spec.id, "done already");
        return Ok(None);
    }
    tracing::info!(job = %spec.id, "starting");
    crate::status::Started::write(out, &spec.id)?;
    let mut report = None;
    match job.work {
        Work::Dataset { seed, task } => {
            let dataset = runs::DatasetJob::new(config, out, seed, task)?;
            if !dataset.cached() {
                runs::collect_dataset(&dataset)?;
            }
        }
        Work::Heuristics(key) => {
            let h = heuristics(config, key);
            cache::save_heuristics(&cache::heuristics_path(out, key), &h)?;
        }
        Work::Reference { seed, key } => {
            let metrics = runs::reference(config, out, seed, key)?;
            cache::save_reference(&cache::reference_path(out, seed, key), metrics)?;
        }
        Work::ModelPlanner { seed, key } => {
            let planned = runs::model_planner(config, out, seed, key)?;
            cache::save_model_planner(&cache::model_planner_path(out, seed, key), &planned)?;
        }
        Work::Init {
            seed,
            key,
            eval_every,
        } => {
            runs::init(config, out, seed, key, eval_every)?;
        }
        Work::Run { seed, run } => {
            let w0 = run.need.key.init().map(|key| runs::w0_path(out, seed, key));
            let result = runs::fine_tune_run(config, out, seed, run, w0.as_deref())?;
            cache::save_run(&cache::run_path(out, seed, &run.need.key), &result)?;
        }
        Work::Figures => {
            check_done(out, spec)?;
            report = Some(crate::write_figures(ctx, wall())?);
        }
    }
    cache::mark_done(out, &spec.id, &spec.stamp)?;
    tracing::info!(job = %spec.id, "done");
    Ok(report)
}

/// Every job `spec` reads the outputs of is done.
fn check_done(out: &Path, spec: &JobSpec) -> Result<(), ReproduceError> {
    let plan = PlanFile::read(out)?;
    let missing = (plan.jobs.iter())
        .filter(|j| spec.after.contains(&j.id) && !PlanFile::done(out, j))
        .map(|j| j.id.clone())
        .collect::<Vec<_>>();
    match missing.is_empty() {
        true => Ok(()),
        false => Err(ReproduceError::Unfinished {
            job: spec.id.clone(),
            count: missing.len(),
            first: missing[0].clone(),
        }),
    }
}

/// The reference policies (random, the heuristics, the planner) on `key`'s task.
fn heuristics(config: &Config, key: &RefKey) -> HeuristicRef {
    let task = config
        .task(&key.task)
        .expect("ReproduceConfig::of and rain_tasks name existing tasks");
    let policies = reference_metrics(config, task, key.episodes)
        .into_iter()
        .map(|(spec, metrics)| (spec.name(), metrics))
        .collect();
    HeuristicRef {
        task: task.name.clone(),
        episodes: key.episodes,
        policies,
    }
}

/// Every job but the figures on the current pool, a stage (a set of kinds) at a time, the
/// seed-free heuristics beside the seeds' stages; `done` after each job, with its users.
pub fn run_local(
    ctx: &JobContext,
    graph: &Graph,
    done: &(impl Fn(&[Experiment]) + Sync),
) -> Result<(), ReproduceError> {
    let stage = |kinds: &[Kind]| -> Result<(), ReproduceError> {
        let jobs: Vec<&Job> = kinds.iter().flat_map(|&k| graph.of(k)).collect();
        jobs.par_iter().with_max_len(1).try_for_each(|job| {
            run_job(ctx, job, Duration::default)?;
            // The progress bars count each seed's items (`Plan::units`), not the seed-free rows.
            if job.spec.kind != Kind::Heuristics {
                done(&job.users);
            }
            Ok(())
        })
    };
    let (heuristics, seeds) = rayon::join(
        || stage(&[Kind::Heuristics]),
        || {
            stage(&[Kind::Dataset])?;
            stage(&[Kind::Reference, Kind::ModelPlanner, Kind::Init])?;
            stage(&[Kind::Run])
        },
    );
    heuristics.and(seeds)
}

/// What the figures read, from the cache: the heuristics' rows of every reference task, and
/// every seed's results in seed order.
pub fn load_results(
    ctx: &JobContext,
) -> Result<(Vec<HeuristicRef>, Vec<SeedResult>), ReproduceError> {
    let (config, out, plan) = (ctx.opts.config, ctx.opts.out_dir, ctx.plan);
    let heuristics = (plan.references.iter())
        .map(|n| cache::load_heuristics(&cache::heuristics_path(out, &n.key), &n.key))
        .collect::<Result<Vec<_>, _>>()?;
    let seed = |seed: u64| -> Result<SeedResult, ReproduceError> {
        let references = (plan.references.iter())
            .map(|n| {
                let path = cache::reference_path(out, seed, &n.key);
                Ok((n.key.clone(), cache::load_reference(&path)?))
            })
            .collect::<Result<_, ReproduceError>>()?;
        let model_planners = (plan.model_planners.iter())
            .map(|n| {
                let path = cache::model_planner_path(out, seed, &n.key);
                Ok((n.key.clone(), cache::load_model_planner(&path)?))
            })
            .collect::<Result<_, ReproduceError>>()?;
        let inits = (plan.inits.iter())
            .map(|n| {
                let eval_every = match n.users.contains(&Experiment::MetaTraining) {
                    true => ctx.r.meta_eval_every,
                    false => 0,
                };
                Ok((
                    n.key,
                    runs::init_curve(config, out, seed, n.key, eval_every)?,
                ))
            })
            .collect::<Result<_, ReproduceError>>()?;
        let runs = (plan.runs.iter())
            .map(|run| {
                let path = cache::run_path(out, seed, &run.need.key);
                Ok((run.need.key.clone(), cache::load_run(&path)?))
            })
            .collect::<Result<_, ReproduceError>>()?;
        Ok(SeedResult {
            seed,
            inits,
            references,
            model_planners,
            runs,
        })
    };
    let seeds = (0..ctx.r.seeds as u64)
        .map(seed)
        .collect::<Result<_, _>>()?;
    Ok((heuristics, seeds))
}

/// How long ago `OUT/plan.json` was first written: a job engine's wall time so far.
pub fn since_plan(out: &Path) -> Duration {
    let written = std::fs::metadata(PlanFile::path(out)).and_then(|m| m.modified());
    written
        .ok()
        .and_then(|t| SystemTime::now().duration_since(t).ok())
        .unwrap_or_default()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn kinds_wait_only_on_kinds_before_them() {
        for (i, kind) in Kind::ALL.into_iter().enumerate() {
            assert_eq!(Kind::parse(kind.name()), Some(kind));
            for before in kind.after() {
                let position = Kind::ALL.iter().position(|k| k == before).unwrap();
                assert!(position < i, "{kind:?} after {before:?}");
            }
        }
        assert_eq!(Kind::parse("bogus"), None);
    }

    fn config() -> (Config, ReproduceConfig) {
        let mut config = Config::default();
        let rain = uavmeta_proto::config::RainZone {
            x0: 1,
            y0: 1,
            x1: 2,
            y1: 2,
        };
        let task = uavmeta_proto::config::TaskConfig::one_off(300.0, Some(rain));
        config.tasks.push(task);
        let r = ReproduceConfig {
            seeds: 2,
            ..ReproduceConfig::default()
        };
        r.write_into(&mut config);
        (config, r)
    }

    #[test]
    fn every_job_waits_on_existing_jobs_of_the_kinds_before_it() {
        let (config, r) = config();
        let plan = crate::plan(&config, &r, &Experiment::ALL);
        let graph = Graph::new(&config, &r, &plan, &Experiment::ALL);
        let jobs = &graph.file.jobs;
        let mut ids: Vec<&str> = jobs.iter().map(|j| j.id.as_str()).collect();
        ids.sort();
        ids.dedup();
        assert_eq!(ids.len(), jobs.len(), "job ids are unique");
        for job in jobs {
            for after in &job.after {
                let found = jobs.iter().find(|j| j.id == *after).expect(after);
                assert!(
                    job.kind.after().contains(&found.kind),
                    "{} after {after}",
                    job.id
                );
            }
            assert!(job
                .stamp
                .starts_with(&format!("config {}", graph.file.config)));
        }
        let count = |kind| graph.file.of(kind).count();
        assert_eq!(count(Kind::Run), 2 * plan.runs.len());
        assert_eq!(count(Kind::Heuristics), plan.references.len());
        assert_eq!(count(Kind::Figures), 1);
        assert_eq!(graph.file.jobs.last().unwrap().after.len(), jobs.len() - 1);
    }

    #[test]
    fn the_fingerprint_ignores_where_jobs_run_only() {
        let (config, r) = config();
        let base = fingerprint(&config, &r);
        let mut slurm = r.clone();
        slurm.slurm.partition = "gpu".into();
        slurm.slurm.cpus_per_task = 4;
        assert_eq!(fingerprint(&config, &slurm), base);
        let mut other = config.clone();
        other.learner.alpha += 1.0;
        assert_ne!(fingerprint(&other, &r), base);
        let more = ReproduceConfig {
            convergence_epochs: 7,
            ..r
        };
        assert_ne!(fingerprint(&config, &more), base);
    }
}
