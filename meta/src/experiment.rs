//! The paper's main claim, measured (SPEC section 6, first items): meta-train on the config's
//! meta-train tasks with datasets sampled from online-DQN replay buffers, then fine-tune on N shots
//! of the unseen task, and compare CQL-MAML, CQL from a random init, DQN and DQN-MAML, with the
//! online DQN agent and the heuristics as reference lines.
//!
//! Steps, all written under the output directory:
//! 1. `datasets/<task>.uavds`: every task's dataset, collected as `[collect]` says (the paper's
//!    `dqn-online`); a file already there from the same world is reused, so reruns and further
//!    seeds do not collect again. The datasets are the same for every seed: the seeds vary
//!    initialisation, splits, shot draws and minibatch order.
//! 2. References on the unseen task: an online DQN agent trained like the collectors (its greedy
//!    policy), and the `random`, `stalest` and `greedy` heuristics.
//! 3. Per seed: meta-train CQL-MAML and DQN-MAML (`seed-S/cql-maml`, `seed-S/dqn-maml`), draw the
//!    N shots once, and fine-tune the four methods on them for E epochs (`seed-S/<method>/train.csv`).
//! 4. `curves.csv` (method, seed, epoch, return) and `summary.md`: per method, over the seeds, the
//!    epochs needed to come within 5% of the final return, the return at epoch 40 and the final
//!    return.
//!
//! "Final return" is the mean over the last `FINAL_EPOCHS` epochs, so one noisy evaluation does
//! not define it; "epochs to within 5%" is the first epoch from which every later evaluated
//! return stays within 5% of it.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use indicatif::ProgressBar;
use uavmeta_actors::collect::collect;
use uavmeta_actors::dqn_online::OnlineDqn;
use uavmeta_actors::heuristics::PolicySpec;
use uavmeta_actors::q_policy::Evaluator;
use uavmeta_actors::rollout::evaluate;
use uavmeta_learner::checkpoint;
use uavmeta_learner::qnet::QNetwork;
use uavmeta_learner::train::{Algorithm, EvaluatePolicy};
use uavmeta_proto::config::{Config, InnerLoss, TaskConfig, TaskRole};
use uavmeta_proto::dataset::DatasetReader;
use uavmeta_proto::stats::{Estimate, PolicyMetrics};

use crate::meta_test::{fine_tune, load_shots, FineTune};
use crate::meta_train::{algorithm_name, dataset_path, meta_train, MetaTrainOptions};
use crate::MetaError;

/// Epochs averaged into a run's final return.
pub const FINAL_EPOCHS: usize = 5;
/// The epoch at which the paper reads off convergence (CQL-MAML under 40 epochs).
pub const READ_AT_EPOCH: usize = 40;
/// Heuristic reference lines.
const HEURISTICS: [&str; 3] = ["random", "stalest", "greedy"];

/// The four methods compared on the unseen task.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Method {
    CqlMaml,
    Cql,
    Dqn,
    DqnMaml,
}

impl Method {
    pub const ALL: [Method; 4] = [Method::CqlMaml, Method::Cql, Method::Dqn, Method::DqnMaml];

    pub fn name(self) -> &'static str {
        match self {
            Method::CqlMaml => algorithm_name(InnerLoss::Cql),
            Method::Cql => "cql",
            Method::Dqn => "dqn",
            Method::DqnMaml => algorithm_name(InnerLoss::Dqn),
        }
    }

    /// The fine-tuning loss.
    fn algorithm(self) -> Algorithm {
        match self {
            Method::CqlMaml | Method::Cql => Algorithm::Cql,
            Method::Dqn | Method::DqnMaml => Algorithm::Dqn,
        }
    }

    /// The inner loss of the meta-training that makes its init; `None` for a random init.
    fn meta_trained(self) -> Option<InnerLoss> {
        match self {
            Method::CqlMaml => Some(InnerLoss::Cql),
            Method::DqnMaml => Some(InnerLoss::Dqn),
            Method::Cql | Method::Dqn => None,
        }
    }
}

pub struct ExperimentOptions<'a> {
    pub config: &'a Config,
    /// The unseen task (role `meta-test`).
    pub task: &'a TaskConfig,
    pub out_dir: &'a Path,
    /// At least 3 for the claim.
    pub seeds: &'a [u64],
    /// N shots of the unseen task (the paper: 500).
    pub shots: usize,
    /// Fine-tuning epochs E.
    pub epochs: usize,
    pub progress: bool,
}

/// One method's fine-tuning curve under one seed.
pub struct Curve {
    pub method: Method,
    pub seed: u64,
    /// Greedy return after each epoch.
    pub returns: Vec<f64>,
}

impl Curve {
    pub fn final_return(&self) -> f64 {
        let tail = &self.returns[self.returns.len().saturating_sub(FINAL_EPOCHS)..];
        tail.iter().sum::<f64>() / tail.len() as f64
    }

    /// The first epoch (from 1) from which every return stays within 5% of the final return.
    pub fn epochs_to_within_5_percent(&self) -> usize {
        let last = self.final_return();
        let outside = |r: &f64| (r - last).abs() > 0.05 * last.abs();
        self.returns
            .iter()
            .rposition(outside)
            .map_or(1, |i| i + 2)
            .min(self.returns.len())
    }

    /// The return after epoch [`READ_AT_EPOCH`], if the run got that far.
    pub fn return_at_read_epoch(&self) -> Option<f64> {
        self.returns.get(READ_AT_EPOCH - 1).copied()
    }
}

/// Everything the experiment measured.
pub struct ExperimentReport {
    pub curves: Vec<Curve>,
    /// Name and metrics of each reference line on the unseen task.
    pub references: Vec<(String, PolicyMetrics)>,
    /// `summary.md`'s text.
    pub summary: String,
}

/// The `--quick` variant of `config`: the same pipeline at a size that runs in about a minute
/// (online DQN for 1000 steps, 5 meta-epochs with one evaluation, 2 evaluation episodes), to check
/// the plumbing, not the claim.
pub fn quick_config(config: &Config) -> Config {
    let mut quick = config.clone();
    quick.collect.dqn_steps = quick.collect.dqn_steps.min(1000);
    quick.collect.learning_starts = quick.collect.learning_starts.min(200);
    quick.collect.eps_decay_steps = quick.collect.eps_decay_steps.min(500);
    quick.meta.meta_epochs = quick.meta.meta_epochs.min(5);
    quick.meta.eval_every = 0;
    quick.learner.eval_episodes = quick.learner.eval_episodes.min(2);
    quick
}

/// Runs the experiment; see the module doc.
pub fn run(opts: &ExperimentOptions) -> Result<ExperimentReport, MetaError> {
    let config = opts.config;
    let datasets = opts.out_dir.join("datasets");
    std::fs::create_dir_all(&datasets).map_err(|source| MetaError::Io {
        path: datasets.clone(),
        action: "create",
        source,
    })?;
    let needed = config
        .tasks_with_role(TaskRole::MetaTrain)
        .chain(std::iter::once(opts.task));
    for task in needed {
        ensure_dataset(
            config,
            task,
            &dataset_path(&datasets, &task.name),
            opts.progress,
        )?;
    }
    let references = references(config, opts.task)?;
    for (name, metrics) in &references {
        tracing::info!(reference = %name, ret = %metrics.ret, aoi = %metrics.aoi, power_mw = %metrics.power_mw, "reference line");
    }

    let mut curves = Vec::new();
    for &seed in opts.seeds {
        let seed_dir = opts.out_dir.join(format!("seed-{seed}"));
        let mut inits: Vec<(InnerLoss, PathBuf)> = Vec::new();
        for inner in [InnerLoss::Cql, InnerLoss::Dqn] {
            let mut meta_config = config.clone();
            meta_config.meta.inner_loss = inner;
            let trained = meta_train(&MetaTrainOptions {
                config: &meta_config,
                datasets: &datasets,
                out_dir: &seed_dir.join(algorithm_name(inner)),
                seed,
                progress: opts.progress,
            })?;
            inits.push((inner, trained.w0));
        }
        let shots = load_shots(
            config,
            opts.task,
            &dataset_path(&datasets, &opts.task.name),
            opts.shots,
            seed,
        )?;
        for method in Method::ALL {
            let mut q = match method.meta_trained() {
                Some(inner) => {
                    let (_, path) = inits
                        .iter()
                        .find(|(i, _)| *i == inner)
                        .expect("both inits were meta-trained above");
                    checkpoint::load(path, config)?.0
                }
                None => QNetwork::new(
                    config.world.observation_len(),
                    config.world.action_count(),
                    &config.learner.hidden,
                    seed,
                ),
            };
            let out = seed_dir.join(method.name());
            let rows = fine_tune(
                &mut q,
                &shots,
                method.algorithm(),
                &FineTune {
                    config,
                    task: opts.task,
                    epochs: opts.epochs,
                    seed,
                    out_dir: Some(&out),
                    progress: opts.progress,
                },
            )?;
            curves.push(Curve {
                method,
                seed,
                returns: rows.iter().map(|r| r.policy.ret.mean).collect(),
            });
        }
    }
    let summary = summarise(opts, &curves, &references);
    write_file(&opts.out_dir.join("summary.md"), &summary)?;
    write_file(&opts.out_dir.join("curves.csv"), &curves_csv(&curves))?;
    Ok(ExperimentReport {
        curves,
        references,
        summary,
    })
}

/// Collects `task`'s dataset into `path` unless a dataset of this world is already there.
fn ensure_dataset(
    config: &Config,
    task: &TaskConfig,
    path: &Path,
    progress: bool,
) -> Result<(), MetaError> {
    if path.exists() {
        let reader = DatasetReader::open(path)?;
        reader.check_world(config)?;
        tracing::info!(dataset = %path.display(), transitions = reader.transitions().len(), "reusing");
        return Ok(());
    }
    let bar = if progress {
        ProgressBar::no_length()
    } else {
        ProgressBar::hidden()
    };
    bar.set_message(format!("collecting {}", task.name));
    collect(config, &task.name, path, &bar)?;
    bar.finish_and_clear();
    Ok(())
}

/// The online DQN agent (trained as the collectors train it, greedy) and the heuristics on `task`.
fn references(
    config: &Config,
    task: &TaskConfig,
) -> Result<Vec<(String, PolicyMetrics)>, MetaError> {
    let task_id = config.task_id(&task.name)? as u32;
    let mut agent = OnlineDqn::new(config, task, task_id, 0, config.collect.seed);
    agent.train().map_err(MetaError::OnlineDqn)?;
    let mut out = vec![(
        "online DQN".to_string(),
        Evaluator::from_config(config, task).evaluate(agent.q_network()),
    )];
    for name in HEURISTICS {
        let spec: PolicySpec = name.parse().expect("the heuristics' names parse");
        let episodes = config.learner.eval_episodes;
        let mut policy = spec
            .build(
                config.world.action_count(),
                config.learner.eval_seed,
                episodes * config.world.horizon as usize,
            )
            .expect("heuristics build for any world");
        out.push((
            name.to_string(),
            evaluate(
                &config.world,
                task,
                policy.as_mut(),
                episodes,
                config.learner.eval_seed,
            ),
        ));
    }
    Ok(out)
}

fn summarise(
    opts: &ExperimentOptions,
    curves: &[Curve],
    references: &[(String, PolicyMetrics)],
) -> String {
    let c = opts.config;
    let mut s = String::new();
    let _ = writeln!(
        s,
        "Unseen task `{}`, {} shots, {} fine-tuning epochs ({} gradient steps each), seeds {:?}; \
         {} meta-train tasks, {} meta-epochs, {} inner step(s), eta_inner {}, eta_outer {}, first order: {}; \
         datasets of {} transitions by `{}` ({} steps); returns are greedy returns over {} episodes.\n",
        opts.task.name,
        opts.shots,
        opts.epochs,
        match c.learner.steps_per_epoch {
            0 => opts.shots.div_ceil(c.learner.batch.min(opts.shots)),
            n => n,
        },
        opts.seeds,
        c.tasks_with_role(TaskRole::MetaTrain).count(),
        c.meta.meta_epochs,
        c.meta.inner_steps,
        c.meta.eta_inner,
        c.meta.eta_outer,
        c.meta.first_order,
        c.collect.transitions,
        c.collect.policy,
        c.collect.dqn_steps,
        c.learner.eval_episodes,
    );
    let _ = writeln!(s, "| method | epochs to within 5% of final | return at epoch {READ_AT_EPOCH} | final return |");
    let _ = writeln!(s, "| --- | --- | --- | --- |");
    for method in Method::ALL {
        let runs: Vec<&Curve> = curves.iter().filter(|c| c.method == method).collect();
        let epochs =
            Estimate::from_samples(runs.iter().map(|c| c.epochs_to_within_5_percent() as f64));
        let at_read: Vec<f64> = runs
            .iter()
            .filter_map(|c| c.return_at_read_epoch())
            .collect();
        let at_read = if at_read.is_empty() {
            "n/a".to_string()
        } else {
            format!("{:.1}", Estimate::from_samples(at_read))
        };
        let last = Estimate::from_samples(runs.iter().map(|c| c.final_return()));
        let _ = writeln!(
            s,
            "| {} | {epochs:.1} | {at_read} | {last:.1} |",
            method.name()
        );
    }
    let _ = writeln!(s, "\n| reference | return | AoI | power (mW) |");
    let _ = writeln!(s, "| --- | --- | --- | --- |");
    for (name, m) in references {
        let _ = writeln!(
            s,
            "| {name} | {:.1} | {:.2} | {:.3} |",
            m.ret, m.aoi, m.power_mw
        );
    }
    s
}

fn curves_csv(curves: &[Curve]) -> String {
    let mut s = String::from("method,seed,epoch,return\n");
    for c in curves {
        for (e, r) in c.returns.iter().enumerate() {
            let _ = writeln!(s, "{},{},{},{r}", c.method.name(), c.seed, e + 1);
        }
    }
    s
}

fn write_file(path: &Path, text: &str) -> Result<(), MetaError> {
    std::fs::write(path, text).map_err(|source| MetaError::Io {
        path: path.to_path_buf(),
        action: "write",
        source,
    })
}
