//! `uavmeta meta-train` and `uavmeta meta-test`: MAML's two phases (Algorithm 4).

use std::path::PathBuf;

use anyhow::Result;
use clap::{Args, ValueEnum};
use uavmeta_learner::progress::OnStep;
use uavmeta_meta::context;
use uavmeta_meta::fine_tune::{meta_test, FineTune, MetaTestOptions};
use uavmeta_meta::meta_train::{meta_train, MetaTrainOptions};
use uavmeta_proto::resources::{self, Job};

use super::common::{ConfigArgs, ShotsArgs, TaskArgs};

#[derive(Args)]
pub struct MetaTrainArgs {
    #[command(flatten)]
    config: ConfigArgs,
    /// Directory with one dataset per meta-train task of the config, named `<task-name>.uavds`
    /// (as `uavmeta collect --out DIR/<task-name>.uavds` writes it).
    #[arg(long)]
    datasets: PathBuf,
    /// Output directory: config.toml, meta_train.csv, w0 checkpoints.
    #[arg(long)]
    out: PathBuf,
    /// Seed of w0's init, the support/query split and the sampling [default: run.seeds[0]].
    #[arg(long)]
    seed: Option<u64>,
    /// Continue from the latest w0 checkpoint in OUT (with its optimiser state) instead of
    /// starting again; an interrupted run continued this way ends where an uninterrupted one does.
    #[arg(long)]
    resume: bool,
    /// What to meta-train: MAML's w0 (Algorithm 4), or the task-inferring context learner
    /// (`[context]`, written as OUT/context).
    #[arg(long, value_enum, default_value_t = Learner::Maml)]
    learner: Learner,
}

#[derive(Clone, Copy, PartialEq, Eq, ValueEnum)]
enum Learner {
    Maml,
    Context,
}

#[derive(Args)]
pub struct MetaTestArgs {
    #[command(flatten)]
    config: ConfigArgs,
    #[command(flatten)]
    task: TaskArgs,
    /// The init meta-train wrote (`OUT/w0`, or `OUT/context`; any extension is ignored).
    #[arg(long)]
    init: PathBuf,
    #[command(flatten)]
    shots: ShotsArgs,
    /// Output directory: train.csv and the final checkpoint.
    #[arg(long)]
    out: PathBuf,
    /// Seed of the shot draw and the minibatch order [default: run.seeds[0]].
    #[arg(long)]
    seed: Option<u64>,
}

pub fn run_train(args: MetaTrainArgs) -> Result<()> {
    let config = args.config.load()?;
    resources::check_memory(&config, Job::MetaTrain)?;
    let seed = args.seed.unwrap_or(config.run.seeds[0]);
    let opts = MetaTrainOptions {
        config: &config,
        datasets: &args.datasets,
        out_dir: &args.out,
        seed,
        progress: true,
        resume: args.resume,
        on_step: OnStep::default(),
    };
    if args.learner == Learner::Context {
        anyhow::ensure!(
            !args.resume,
            "--resume: the context learner trains in one go; run it again without --resume"
        );
        let run = context::meta_train_to_dir(&opts)?;
        for (task, ret) in &run.zero_shot {
            println!("  {task}: zero-shot return {ret:.1} (code read from its query set)");
        }
        println!("context model: {}", run.model.display());
        return Ok(());
    }
    let result = meta_train(&opts)?;
    if let Some(last) = result.rows.last() {
        println!(
            "meta-epoch {}: meta-loss {:.4}",
            last.epoch.epoch, last.epoch.meta_loss
        );
        if let Some(evaluation) = &last.evaluation {
            let returns = evaluation.adapted.iter().zip(&evaluation.zero_shot);
            for (task, (adapted, zero_shot)) in result.tasks.iter().zip(returns) {
                println!(
                    "  {}: greedy return after adaptation {adapted:.1} (w0 zero-shot {zero_shot:.1})",
                    task.name
                );
            }
        }
    }
    println!(
        "w0: {}; per-meta-epoch figures: {}",
        result.w0.display(),
        args.out.join("meta_train.csv").display()
    );
    Ok(())
}

pub fn run_test(args: MetaTestArgs) -> Result<()> {
    let mut config = args.config.load()?;
    let task = args.task.resolve(&mut config)?;
    resources::check_memory(&config, Job::Train)?;
    let seed = args.seed.unwrap_or(config.run.seeds[0]);
    let result = meta_test(&MetaTestOptions {
        fine_tune: FineTune {
            config: &config,
            task: &task,
            epochs: args.shots.epochs.unwrap_or(config.learner.epochs),
            seed,
            out_dir: Some(&args.out),
            progress: true,
            on_step: OnStep::default(),
        },
        init: &args.init,
        dataset: &args.shots.dataset,
        shots: args.shots.shots,
    })?;
    let init = &result.init;
    println!(
        "init, zero-shot: return {:.1}, AoI {:.2}, power {:.3} mW",
        init.ret, init.aoi, init.power_mw
    );
    if let Some(last) = result.rows.last() {
        println!(
            "{}: return {:.1}, AoI {:.2}, power {:.3} mW",
            last.kept(),
            last.policy.ret,
            last.policy.aoi,
            last.policy.power_mw
        );
    }
    println!(
        "per-epoch figures: {}",
        args.out.join("train.csv").display()
    );
    Ok(())
}
