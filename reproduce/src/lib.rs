//! `uavmeta reproduce`: the paper's section V experiments (figures 4-9) over several seeds, each
//! figure beside the claim of docs/MODEL.md section 6 it supports, decided from the measured
//! numbers.
//!
//! A crate of its own, apart from the MAML crate it measures: the harness links the chart library
//! and a thread pool, and fails in ways (a figure that cannot be drawn, a config without rain
//! tasks) that are no part of meta-learning's error type. It consumes everything below it: the
//! world of `uavmeta-world`, behaviour policies and collection of `uavmeta-actors`, offline
//! training and checkpoints of `uavmeta-learner`, meta-training and meta-testing of `uavmeta-meta`,
//! and `uavmeta-plot`'s charts; its results are files under an output directory.
//!
//! It owns the orchestration; the pieces are:
//! - [`runs`]: one seed's pipeline and its cache under `OUT/cache/seed-S/` (datasets, online DQN
//!   agents, meta-trained w0s), and the plan of fine-tuning runs shared between experiments;
//! - [`plan`]: that plan as a graph of jobs over the cache (`OUT/plan.json`), the one function
//!   that runs a job and the local engine; [`cache`]: the jobs' results and completion markers;
//! - [`slurm`]: the same graph submitted to Slurm as one job array per kind of job;
//! - [`status`]: where a plan stands, whichever engine runs it: jobs done, running and left, their
//!   times and the time left, read from the cache (and squeue);
//! - [`figures`]: per experiment, its CSV files, PNG charts ([`uavmeta_plot`]) and `summary.md`;
//! - [`claims`]: curve statistics and the yes / partly / no rules;
//! - [`ReproduceConfig`]: the `[reproduce]` section, which this crate alone reads and checks.
//!
//! Pipeline of [`run`] (the local engine; [`submit`] hands the same jobs to Slurm):
//! 1. Check `[reproduce]` against the tasks, and build one [`runs::Plan`] for the selected
//!    experiments: every dataset, reference agent, w0 and fine-tuning run they need, each once
//!    (CQL-MAML on the first `meta_tasks` tasks is meta-trained once per seed and serves figures
//!    4, 5, 6, 8 and 9); write its graph of jobs, `OUT/plan.json`.
//! 2. The reference lines (random, stalest, greedy, the planner), which depend on no seed, and
//!    beside them on the same pool of `jobs` threads:
//! 3. Seeds 0..N-1, each job through the same code paths as the
//!    runtime: `collect` with the online DQN behaviour policy (`collect.seed + s`), its agent as
//!    the online reference, `meta_train`, and `fine_tune`'s `fine_tune` with the greedy policy
//!    evaluated after every epoch. Every result goes into the cache; a job already done is
//!    skipped.
//! 4. The figures job reads the results back from the cache in seed order (so they do not
//!    depend on `jobs` or the engine): each experiment writes `OUT/<experiment>/` and returns its
//!    claims; `OUT/summary.md` gathers every claim table.

mod cache;
mod claims;
mod config;
mod figures;
pub mod plan;
mod runs;
pub mod slurm;
pub mod status;

pub use config::ReproduceConfig;
pub use plan::{JobSelector, Kind};

use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use indicatif::{MultiProgress, ProgressBar, ProgressDrawTarget, ProgressStyle};
use uavmeta_actors::collect::CollectError;
use uavmeta_meta::{create_dir, MetaError};
use uavmeta_proto::config::{Config, ConfigError, TaskConfig, TaskRole};
use uavmeta_proto::stats::PolicyMetrics;

use claims::Claim;
use plan::{Graph, JobContext};
use runs::{meta_train_tasks, InitKey, Plan};

/// Everything a reproduction can fail on.
#[derive(Debug, thiserror::Error)]
pub enum ReproduceError {
    #[error("{origin}: the resilience experiment needs rain tasks (role = \"meta-test\" with a `rain` zone); the config has none")]
    NoRainTasks { origin: String },
    #[error("cannot start the reproduction's worker threads")]
    Threads(#[from] rayon::ThreadPoolBuildError),
    #[error(transparent)]
    Plot(#[from] uavmeta_plot::PlotError),
    /// Also a config, dataset, checkpoint or training error: `MetaError` wraps each already, with
    /// the same message.
    #[error(transparent)]
    Meta(#[from] MetaError),
    #[error(transparent)]
    Collect(#[from] CollectError),
    #[error("{}: {message}", path.display())]
    Cache { path: PathBuf, message: String },
    #[error("no {job} in the plan (OUT/plan.json lists its jobs)")]
    NoSuchJob { job: String },
    #[error("{} holds the plan of another config or choice of experiments: run a job with the --config, --set, --quick, --seeds and --experiment the plan was written with, or write the plan again", path.display())]
    OtherPlan { path: PathBuf },
    #[error("job `{job}` reads {count} jobs that are not done, the first `{first}`; run them first (`uavmeta reproduce --status` shows what is left)")]
    Unfinished {
        job: String,
        count: usize,
        first: String,
    },
    #[error(transparent)]
    Slurm(#[from] slurm::SlurmError),
}

/// One of the paper's experiments.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Experiment {
    /// Figure 4: CQL-MAML's meta-training.
    MetaTraining,
    /// Figure 5: the four methods on the unseen task.
    Convergence,
    /// Figure 6: CQL and CQL-MAML on 100, 300 and 500 shots.
    Shots,
    /// Figure 7: CQL-MAML meta-trained on 2 to 10 tasks.
    Tasks,
    /// Figure 8: AoI and power after 50 epochs.
    AoiPower,
    /// Figure 9: the rain tasks.
    Resilience,
    /// Not a figure of the paper: the online DQN agents behind every dataset, against the
    /// heuristics on each task (docs/MODEL.md section 5 asks for heuristic level before sampling).
    OnlineDqn,
}

impl Experiment {
    pub const ALL: [Experiment; 7] = [
        Experiment::OnlineDqn,
        Experiment::MetaTraining,
        Experiment::Convergence,
        Experiment::Shots,
        Experiment::Tasks,
        Experiment::AoiPower,
        Experiment::Resilience,
    ];

    /// What `--experiment` accepts: `all` or one experiment's name.
    pub const CHOICES: [&'static str; 8] = [
        "all",
        "meta-training",
        "convergence",
        "shots",
        "tasks",
        "aoi-power",
        "resilience",
        "online-dqn",
    ];

    /// Its name on the command line and its output directory.
    pub fn name(self) -> &'static str {
        Self::CHOICES[1 + self as usize]
    }

    /// The title of its summary, which names its figure of the paper.
    pub fn title(self) -> &'static str {
        match self {
            Experiment::MetaTraining => "Figure 4: meta-training",
            Experiment::Convergence => "Figure 5: convergence on the unseen task",
            Experiment::Shots => "Figure 6: number of shots",
            Experiment::Tasks => "Figure 7: number of meta-training tasks",
            Experiment::AoiPower => "Figure 8: AoI and power",
            Experiment::Resilience => "Figure 9: resilience to rain",
            Experiment::OnlineDqn => "The behaviour agents: online DQN against the heuristics",
        }
    }

    /// The experiments one of [`Experiment::CHOICES`] selects.
    pub fn select(choice: &str) -> Option<Vec<Experiment>> {
        if choice == "all" {
            return Some(Self::ALL.to_vec());
        }
        Self::ALL
            .into_iter()
            .find(|e| e.name() == choice)
            .map(|e| vec![e])
    }
}

/// One reproduction.
pub struct ReproduceOptions<'a> {
    /// `[reproduce]` sizes the experiments; [`quick_config`] already applied for `--quick`.
    pub config: &'a Config,
    pub experiments: &'a [Experiment],
    /// The run checks plumbing only; summaries say so.
    pub quick: bool,
    pub out_dir: &'a Path,
    /// Worker threads: items of the plan (of any seed) run this many at a time.
    pub jobs: usize,
    pub progress: bool,
    /// The command line, and the git commit of the build, for the summaries' headers.
    pub command: &'a str,
    pub commit: &'a str,
}

/// What a reproduction wrote.
pub struct ReproduceReport {
    /// `OUT/summary.md`'s text.
    pub summary: String,
    pub summary_path: PathBuf,
    pub wall: Duration,
}

/// The `--quick` variant of `config`: the same pipeline at a size that runs in well under a
/// minute (online DQN for 1000 steps, [32, 32] networks, 3 meta-epochs, a handful of fine-tuning
/// epochs, 2 seeds, 2 evaluation episodes), to check the plumbing, not the claims. Fails only on a
/// `[reproduce]` section that breaks its own rules.
pub fn quick_config(config: &Config) -> Result<Config, ConfigError> {
    let mut quick = config.clone();
    let mut r: ReproduceConfig = config.reproduce.read(&config.origin)?;
    let c = &mut quick.collect;
    c.dqn.steps = c.dqn.steps.min(1000).max(c.transitions);
    c.dqn.replay_capacity = c.dqn.replay_capacity.min(1000).max(c.transitions);
    c.dqn.learning_starts = c.dqn.learning_starts.min(200);
    c.dqn.eps_decay_steps = c.dqn.eps_decay_steps.min(500);
    c.dqn.hidden = vec![32, 32];
    quick.learner.hidden = vec![32, 32];
    quick.learner.eval_episodes = quick.learner.eval_episodes.min(2);
    quick.learner.steps_per_epoch = quick.learner.steps_per_epoch.min(10);
    quick.meta.meta_epochs = quick.meta.meta_epochs.min(3);
    r.seeds = r.seeds.min(2);
    r.convergence_epochs = r.convergence_epochs.min(5);
    r.tasks_epochs = r.tasks_epochs.min(3);
    r.aoi_power_epoch = r.aoi_power_epoch.min(3);
    r.resilience_epochs = r.resilience_epochs.min(4);
    r.resilience_eval_episodes = r.resilience_eval_episodes.min(2);
    r.meta_eval_every = 1;
    // A narrow single search: the planner's rows only have to exist here, and its default
    // portfolio costs about half a minute per reference task (docs/BENCHMARKS.md).
    quick.planner.beam_width = quick.planner.beam_width.min(16);
    quick.planner.h_power_weights.truncate(1);
    r.write_into(&mut quick);
    Ok(quick)
}

/// The rain tasks of figure 9: meta-test tasks with a rain zone.
pub fn rain_tasks(config: &Config) -> impl Iterator<Item = &TaskConfig> {
    config
        .tasks_with_role(TaskRole::MetaTest)
        .filter(|t| t.rain.is_some())
}

/// Every task an online agent makes data for, with the episodes its references are keyed by: the
/// meta-train tasks and the unseen task (`learner.eval_episodes`), then the rain tasks
/// (`reproduce.resilience_eval_episodes`, as figure 9 evaluates them).
pub fn agent_tasks<'c>(config: &'c Config, r: &ReproduceConfig) -> Vec<(&'c TaskConfig, usize)> {
    config
        .tasks_with_role(TaskRole::MetaTrain)
        .chain(config.task(&r.unseen_task).ok())
        .map(|t| (t, config.learner.eval_episodes))
        .chain(rain_tasks(config).map(|t| (t, r.resilience_eval_episodes)))
        .collect()
}

/// The heuristics' figures on a task over a number of episodes.
#[derive(Debug, Clone)]
pub struct HeuristicRef {
    pub task: String,
    pub episodes: usize,
    pub policies: Vec<(&'static str, PolicyMetrics)>,
}

impl HeuristicRef {
    /// The mean return of policy `name`, if it is one of them.
    fn ret(&self, name: &str) -> Option<f64> {
        let found = self.policies.iter().find(|(n, _)| *n == name);
        found.map(|(_, m)| m.ret.mean)
    }
}

/// Checks `[reproduce]` and builds the plan of the selected experiments.
fn checked_plan(opts: &ReproduceOptions) -> Result<(ReproduceConfig, Plan), ReproduceError> {
    let config = opts.config;
    let r = ReproduceConfig::of(config).map_err(MetaError::from)?;
    if opts.experiments.contains(&Experiment::Resilience) && rain_tasks(config).next().is_none() {
        return Err(ReproduceError::NoRainTasks {
            origin: config.origin.clone(),
        });
    }
    let plan = plan(config, &r, opts.experiments);
    Ok((r, plan))
}

/// Runs the selected experiments on the local pool; see the module doc.
pub fn run(opts: &ReproduceOptions) -> Result<ReproduceReport, ReproduceError> {
    let started = Instant::now();
    let (r, plan) = checked_plan(opts)?;
    let graph = Graph::new(opts.config, &r, &plan, opts.experiments);
    create_dir(opts.out_dir)?;
    graph.write(opts.out_dir)?;
    let ctx = JobContext {
        opts,
        r: &r,
        plan: &plan,
    };
    let bars = progress_bars(opts, &plan, r.seeds);
    let done = |users: &[Experiment]| {
        let used = bars.iter().filter(|(e, _)| users.contains(e));
        used.for_each(|(_, bar)| bar.inc(1));
    };
    worker_pool(opts.jobs)?.install(|| plan::run_local(&ctx, &graph, &done))?;
    for (_, bar) in &bars {
        bar.finish_and_clear();
    }
    let figures = graph
        .of(Kind::Figures)
        .next()
        .expect("every plan ends in figures");
    let report = plan::run_job(&ctx, figures, || started.elapsed())?;
    Ok(report.expect("the figures job returns its report"))
}

/// Runs one job of the plan `OUT/plan.json` holds (written by [`run`] or [`submit`] with the same
/// options): a no-op when it is done; the figures job's report.
pub fn run_job(
    opts: &ReproduceOptions,
    job: &JobSelector,
) -> Result<Option<ReproduceReport>, ReproduceError> {
    let (r, plan) = checked_plan(opts)?;
    let graph = Graph::new(opts.config, &r, &plan, opts.experiments);
    graph.check_written(opts.out_dir)?;
    let job = graph.find(job)?;
    let ctx = JobContext {
        opts,
        r: &r,
        plan: &plan,
    };
    plan::run_job(&ctx, job, || plan::since_plan(opts.out_dir))
}

/// Writes the plan and submits every job not done to Slurm (`slurm::submit`, with
/// `[reproduce.slurm]`); `job_command` runs one job when `--stage KIND --index N` follow it.
pub fn submit(
    opts: &ReproduceOptions,
    job_command: &[String],
) -> Result<slurm::Submitted, ReproduceError> {
    let (r, plan) = checked_plan(opts)?;
    let graph = Graph::new(opts.config, &r, &plan, opts.experiments);
    create_dir(opts.out_dir)?;
    graph.write(opts.out_dir)?;
    slurm::submit(opts.out_dir, &graph.file, &r.slurm, job_command)
}

/// Every experiment's files, from the cache; `wall` is the reproduction's time so far.
fn write_figures(ctx: &JobContext, wall: Duration) -> Result<ReproduceReport, ReproduceError> {
    let (opts, r) = (ctx.opts, ctx.r);
    let (heuristics, seeds) = plan::load_results(ctx)?;
    let fig = figures::Context {
        config: opts.config,
        reproduce: r,
        seeds: &seeds,
        heuristics: &heuristics,
    };
    let mut sections = Vec::new();
    for &experiment in opts.experiments {
        let dir = opts.out_dir.join(experiment.name());
        create_dir(&dir)?;
        let section = figures::write(&fig, experiment, &dir)?;
        let text = format!(
            "{}\n{}",
            header(opts, r, experiment.title(), wall),
            section.body
        );
        cache::write(&dir.join("summary.md"), &text)?;
        sections.push((experiment, section));
    }
    let mut summary = header(opts, r, "Reproduction of the paper's section V", wall);
    let claims: Vec<Claim> = sections
        .iter()
        .flat_map(|(_, s)| s.claims.iter().cloned())
        .collect();
    let _ = writeln!(summary, "## Every claim (docs/MODEL.md section 6)\n");
    summary.push_str(&claims::table(&claims));
    for (experiment, _) in &sections {
        let _ = write!(
            summary,
            "\n- {}: [`{name}/summary.md`]({name}/summary.md)",
            experiment.title(),
            name = experiment.name()
        );
    }
    summary.push('\n');
    let summary_path = opts.out_dir.join("summary.md");
    cache::write(&summary_path, &summary)?;
    Ok(ReproduceReport {
        summary,
        summary_path,
        wall,
    })
}

/// The header of every summary: how it was made.
fn header(opts: &ReproduceOptions, r: &ReproduceConfig, title: &str, wall: Duration) -> String {
    let mut s = format!("# {title}\n\n");
    let _ = writeln!(s, "- command: `{}`", opts.command);
    let _ = writeln!(s, "- commit: {}", opts.commit);
    let _ = writeln!(
        s,
        "- config: {} (meta-train tasks {}, unseen task `{}`, {} meta-epochs, {} gradient steps per epoch, \
         {} evaluation episodes; datasets of {} transitions by `{}` after {} online steps)",
        opts.config.origin,
        r.meta_tasks,
        r.unseen_task,
        opts.config.meta.meta_epochs,
        match opts.config.learner.steps_per_epoch {
            0 => "one pass of".to_string(),
            n => n.to_string(),
        },
        opts.config.learner.eval_episodes,
        opts.config.collect.transitions,
        opts.config.collect.policy,
        opts.config.collect.dqn.steps,
    );
    let _ = writeln!(
        s,
        "- seeds: 0..{} (seed s collects with collect.seed + s = {}..{}); every figure is a mean over seeds with a 95% confidence band",
        r.seeds - 1,
        opts.config.collect.seed,
        opts.config.collect.seed + r.seeds as u64 - 1
    );
    let _ = writeln!(s, "- wall time: {:.1} min", wall.as_secs_f64() / 60.0);
    if opts.quick {
        let _ = writeln!(
            s,
            "\n**`--quick`: a tiny run that checks the plumbing only; its numbers say nothing about the claims.**"
        );
    }
    s.push('\n');
    s
}

/// Every item the selected experiments need from each seed.
fn plan(config: &Config, r: &ReproduceConfig, experiments: &[Experiment]) -> Plan {
    let mut plan = Plan::default();
    let unseen =
        |method, shots, meta_tasks| figures::unseen_key(config, r, method, shots, meta_tasks);
    let episodes = config.learner.eval_episodes;
    // The model-based section's reference line, beside every figure that compares methods.
    let model_planner = |plan: &mut Plan, task: &str, shots, episodes, e| {
        if figures::compared(config).iter().any(|m| m.model_based()) {
            let task = task.to_string();
            plan.model_planner(
                runs::ModelPlannerKey {
                    task,
                    shots,
                    episodes,
                },
                e,
            );
        }
    };
    for &e in experiments {
        match e {
            Experiment::MetaTraining => {
                let key = InitKey {
                    kind: runs::W0,
                    tasks: r.meta_tasks,
                };
                plan.init(config, key, e);
                // The summary sets each task's returns beside its online agent's.
                for task in meta_train_tasks(config, r.meta_tasks) {
                    plan.reference(&task.name, episodes, e);
                }
            }
            Experiment::Convergence => {
                for method in figures::fine_tuned(config) {
                    let key = unseen(method, r.main_shots, r.meta_tasks);
                    plan.run(config, key, r.convergence_epochs, false, e);
                }
                plan.reference(&r.unseen_task, episodes, e);
                model_planner(&mut plan, &r.unseen_task, r.main_shots, episodes, e);
            }
            Experiment::Shots => {
                for &shots in &r.shots {
                    for method in figures::compared(config) {
                        let key = unseen(method, shots, r.meta_tasks);
                        plan.run(config, key, r.convergence_epochs, false, e);
                    }
                    model_planner(&mut plan, &r.unseen_task, shots, episodes, e);
                }
            }
            Experiment::Tasks => {
                // A method from a random init has one key for every task count.
                for &n in &r.task_counts {
                    for method in figures::compared(config) {
                        let key = unseen(method, r.main_shots, n);
                        plan.run(config, key, r.tasks_epochs, false, e);
                    }
                }
                plan.reference(&r.unseen_task, episodes, e);
                model_planner(&mut plan, &r.unseen_task, r.main_shots, episodes, e);
            }
            Experiment::AoiPower => {
                for method in figures::compared(config) {
                    let key = unseen(method, r.main_shots, r.meta_tasks);
                    plan.run(config, key, r.aoi_power_epoch, false, e);
                }
                plan.reference(&r.unseen_task, episodes, e);
                model_planner(&mut plan, &r.unseen_task, r.main_shots, episodes, e);
            }
            Experiment::OnlineDqn => {
                for (task, episodes) in agent_tasks(config, r) {
                    plan.reference(&task.name, episodes, e);
                }
            }
            Experiment::Resilience => {
                for (i, task) in rain_tasks(config).enumerate() {
                    for method in figures::compared(config) {
                        let key = figures::rain_key(config, r, task, method);
                        let path = i == 0 && figures::PATHS.contains(&method);
                        plan.run(config, key, r.resilience_epochs, path, e);
                    }
                    plan.reference(&task.name, r.resilience_eval_episodes, e);
                    let rain_episodes = r.resilience_eval_episodes;
                    model_planner(&mut plan, &task.name, r.main_shots, rain_episodes, e);
                }
            }
        }
    }
    plan
}

/// The pool every stage of a reproduction runs on: `jobs` worker threads.
///
/// libtorch's OpenMP thread count is a per-thread setting: a new thread starts with one per
/// core, and two workers spin-waiting on each other's cores ran no faster than one
/// (docs/BENCHMARKS.md, "Threads"). Each worker takes the count main set.
fn worker_pool(jobs: usize) -> Result<rayon::ThreadPool, ReproduceError> {
    let torch_threads = tch::get_num_threads();
    Ok(rayon::ThreadPoolBuilder::new()
        .num_threads(jobs.max(1))
        .start_handler(move |_| tch::set_num_threads(torch_threads))
        .build()?)
}

/// One progress bar per experiment, counting the items of the plan it uses over every seed.
fn progress_bars(
    opts: &ReproduceOptions,
    plan: &Plan,
    seeds: usize,
) -> Vec<(Experiment, ProgressBar)> {
    let multi = MultiProgress::with_draw_target(if opts.progress {
        ProgressDrawTarget::stderr()
    } else {
        ProgressDrawTarget::hidden()
    });
    let style = ProgressStyle::with_template("{prefix:>14} {bar:30} {pos}/{len} {elapsed}/{eta}")
        .expect("the template is valid");
    opts.experiments
        .iter()
        .map(|&e| {
            let bar = multi.add(ProgressBar::new(plan.units(e) * seeds as u64));
            bar.set_style(style.clone());
            bar.set_prefix(e.name());
            (e, bar)
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use uavmeta_proto::method::Method;

    #[test]
    fn choices_select_their_experiments() {
        assert_eq!(Experiment::select("all").unwrap(), Experiment::ALL.to_vec());
        for e in Experiment::ALL {
            assert_eq!(Experiment::select(e.name()).unwrap(), vec![e]);
        }
        assert_eq!(Experiment::AoiPower.name(), "aoi-power");
        assert!(Experiment::select("bogus").is_none());
    }

    #[test]
    fn all_experiments_share_one_cql_maml_init_and_its_runs() {
        let mut config = Config::default();
        let r = ReproduceConfig {
            task_counts: vec![2, 8],
            ..ReproduceConfig::default()
        };
        config.tasks.push(TaskConfig::one_off(
            300.0,
            Some(uavmeta_proto::config::RainZone {
                x0: 1,
                y0: 1,
                x1: 2,
                y1: 2,
            }),
        ));
        let plan = plan(&config, &r, &Experiment::ALL);
        // CQL-MAML (w0), CQL-pretrain and CQL-context on 2 and 8 tasks, DQN-MAML on 8.
        assert_eq!(plan.inits.len(), 7);
        let main = plan
            .runs
            .iter()
            .find(|r| {
                r.need.key.method == Method::CQL_MAML
                    && r.need.key.task == "lambda-300"
                    && r.need.key.shots == 500
                    && r.need.key.meta_tasks == 8
            })
            .unwrap();
        assert_eq!(main.epochs, 100);
        assert_eq!(
            main.need.users,
            vec![
                Experiment::Convergence,
                Experiment::Shots,
                Experiment::Tasks,
                Experiment::AoiPower
            ]
        );
        // 6 methods and each baseline from w0 and from a random init; the 4 CQL inits and the
        // baselines at 2 more shot counts and on the rain task; on 2 tasks, the methods with an
        // init (3 CQL inits and the baselines from w0).
        let b = config.learner.baselines.len();
        assert_eq!(
            plan.runs.len(),
            (6 + 2 * b) + (4 + 2 * b) * 2 + (4 + 2 * b) + (3 + b)
        );
        assert_eq!(plan.runs.iter().filter(|r| r.trajectory).count(), 2);
        // Dyna-CQL is a baseline: the planner in the fitted world of each shot count of the
        // unseen task (100, 300, 500) and of the rain task's shots.
        assert_eq!(plan.model_planners.len(), 3 + 1);
    }

    #[test]
    fn quick_keeps_datasets_collectable() {
        let quick = quick_config(&Config::default()).unwrap();
        assert!(quick.collect.dqn.steps >= quick.collect.transitions);
        assert!(quick.collect.dqn.replay_capacity >= quick.collect.transitions);
        quick.validate().unwrap();
        let r: ReproduceConfig = quick.reproduce.read(&quick.origin).unwrap();
        assert_eq!((r.seeds, r.meta_eval_every), (2, 1));
    }
}
