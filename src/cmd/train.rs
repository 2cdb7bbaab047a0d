//! `uavmeta train`: an offline algorithm (CQL, DQN, ..) on N shots of one task's dataset,
//! evaluating the greedy policy in the task's world after every epoch.

use std::path::PathBuf;

use anyhow::{Context, Result};
use clap::Args;
use uavmeta_actors::policy::q_policy::Evaluator;
use uavmeta_learner::checkpoint;
use uavmeta_learner::progress::OnStep;
use uavmeta_learner::qnet::QNetworkConfig;
use uavmeta_learner::train::{train, TrainOptions};
use uavmeta_learner::transitions::load_shots;
use uavmeta_proto::method::Algo;
use uavmeta_proto::resources::{self, Job};

use super::common::{ConfigArgs, ShotsArgs, TaskArgs};

#[derive(Args)]
pub struct TrainArgs {
    #[command(flatten)]
    config: ConfigArgs,
    #[command(flatten)]
    task: TaskArgs,
    /// The offline algorithm: cql (eq. 8), dqn (eq. 7) or any other registered one.
    #[arg(long, value_parser = |s: &str| s.parse::<Algo>())]
    algo: Algo,
    #[command(flatten)]
    shots: ShotsArgs,
    /// `random` (a network seeded by --seed) or a checkpoint to start from.
    #[arg(long, default_value = "random")]
    init: String,
    /// Output directory: train.csv and the `final` checkpoint.
    #[arg(long)]
    out: PathBuf,
    /// Seed of the random init, the shot draw and the minibatch order [default: run.seeds[0]].
    #[arg(long)]
    seed: Option<u64>,
    /// Seed of the random init alone [default: --seed]: to vary the init with the shots and the
    /// order fixed. A launch's CQL row is `--seed S --init-seed S+1`, S its run seed.
    #[arg(long)]
    init_seed: Option<u64>,
}

pub fn run(args: TrainArgs) -> Result<()> {
    let mut config = args.config.load()?;
    let task = args.task.resolve(&mut config)?;
    // Saved beside the final checkpoint, so the flags that change training go into the config.
    if let Some(epochs) = args.shots.epochs {
        config.learner.epochs = epochs;
    }
    resources::check_memory(&config, Job::Train)?;
    let seed = args.seed.unwrap_or(config.run.seeds[0]);
    let shots = args.shots.shots;
    let mut q = match (args.init.as_str(), args.init_seed) {
        ("random", init_seed) => QNetworkConfig::for_world(&config.world, &config.learner.hidden)
            .init(init_seed.unwrap_or(seed)),
        (init, Some(_)) => {
            anyhow::bail!(
                "--init-seed seeds a random init, but --init is `{init}`: drop one of the two"
            )
        }
        (init, None) => checkpoint::load(init.as_ref(), &config)?.0,
    };
    let data = load_shots(&config, &task, &args.shots.dataset, shots, seed)?;
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("{}: cannot create the directory", args.out.display()))?;
    let opts = TrainOptions {
        algorithm: args.algo,
        config: &config,
        seed,
        out_dir: Some(&args.out),
        progress: true,
        on_step: OnStep::default(),
    };
    let rows = train(
        &mut q,
        &data.data,
        &opts,
        &mut Evaluator::from_config(&config, &task).with_model(&data.rows),
    )?;
    if let Some(last) = rows.last() {
        println!(
            "{} on {} shots of `{}`, {}: return {:.1}, AoI {:.2}, power {:.3} mW, outages {:.1}, mean Q {:.1}",
            args.algo, shots, task.name, last.kept(), last.policy.ret, last.policy.aoi, last.policy.power_mw, last.policy.outages, last.mean_q
        );
    }
    println!(
        "per-epoch figures: {}; checkpoint: {}",
        args.out.join("train.csv").display(),
        checkpoint::CheckpointPaths::new(&args.out.join("final"))
            .weights
            .display()
    );
    Ok(())
}
