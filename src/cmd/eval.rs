//! `uavmeta eval`: the greedy policy of a checkpoint on one task's true world, Monte-Carlo over
//! fixed episodes, with 95% confidence intervals.

use std::path::PathBuf;

use anyhow::Result;
use clap::Args;
use uavmeta_actors::policy::q_policy::Evaluator;
use uavmeta_learner::checkpoint;
use uavmeta_learner::train::EvaluatePolicy;

use super::common::{ConfigArgs, TaskArgs};

#[derive(Args)]
pub struct EvalArgs {
    #[command(flatten)]
    config: ConfigArgs,
    #[command(flatten)]
    task: TaskArgs,
    /// The checkpoint (`DIR/final`; any extension is ignored).
    #[arg(long)]
    checkpoint: PathBuf,
    /// Episodes [default: learner.eval_episodes].
    #[arg(long, value_parser = clap::value_parser!(u64).range(1..))]
    episodes: Option<u64>,
    /// Seed of the episodes [default: learner.eval_seed].
    #[arg(long)]
    seed: Option<u64>,
}

pub fn run(args: EvalArgs) -> Result<()> {
    let mut config = args.config.load()?;
    let task = args.task.resolve(&mut config)?;
    let (q, meta) = checkpoint::load(&args.checkpoint, &config)?;
    let episodes = match args.episodes {
        Some(n) => usize::try_from(n)?,
        None => config.learner.eval_episodes,
    };
    let seed = args.seed.unwrap_or(config.learner.eval_seed);
    let m = Evaluator::new(&config.world, &task, episodes, seed).evaluate(&q);
    println!(
        "{} ({}, epoch {}) on `{}`, {} episodes seeded {seed}:",
        args.checkpoint.display(),
        meta.algorithm,
        meta.epoch,
        task.name,
        m.episodes
    );
    println!("  return    {:.1}", m.ret);
    println!("  AoI       {:.3}", m.aoi);
    println!("  power mW  {:.4}", m.power_mw);
    println!("  outages   {:.2}", m.outages);
    Ok(())
}
