//! `uavmeta eval`: the greedy policy of a checkpoint on one task's true world, Monte-Carlo over
//! fixed episodes, with 95% confidence intervals.

use std::path::PathBuf;

use anyhow::Result;
use clap::Args;
use uavmeta_actors::policy::q_policy::Evaluator;
use uavmeta_learner::checkpoint;
use uavmeta_proto::config::{Config, TaskConfig};
use uavmeta_proto::resources::{self, Job};
use uavmeta_proto::stats::{EpisodeMetrics, PolicyMetrics};
use uavmeta_world::heuristics::PolicySpec;
use uavmeta_world::rollout::evaluate;

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
    #[arg(long, value_parser = clap::builder::RangedU64ValueParser::<usize>::new().range(1..))]
    episodes: Option<usize>,
    /// Seed of the episodes [default: learner.eval_seed].
    #[arg(long)]
    seed: Option<u64>,
    /// Also print every episode (its start cell and metrics) and count the start cells that trap
    /// the policy: episodes whose return is below the random policy's mean on the task.
    #[arg(long)]
    per_episode: bool,
}

pub fn run(args: EvalArgs) -> Result<()> {
    let mut config = args.config.load()?;
    let task = args.task.resolve(&mut config)?;
    let episodes = args.episodes.unwrap_or(config.learner.eval_episodes);
    match args.episodes {
        Some(n) => resources::check_memory_with_episodes(
            &config,
            Job::Eval,
            format!("--episodes = {n}"),
            resources::evaluation_worlds(&config, &task, n, true),
        )?,
        None => resources::check_memory(&config, Job::Eval)?,
    }
    let (q, meta) = checkpoint::load(&args.checkpoint, &config)?;
    let seed = args.seed.unwrap_or(config.learner.eval_seed);
    // Every episode once: the summary below and, with --per-episode, the listing.
    let runs = Evaluator::new(&config.world, &task, episodes, seed).episodes(&q);
    let m = PolicyMetrics::from_episodes(&runs.iter().map(|(_, e)| *e).collect::<Vec<_>>());
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
    if args.per_episode {
        print_episodes(&config, &task, &runs, seed);
    }
    Ok(())
}

/// One line per episode, then how many fall below the random policy's mean return (evaluated
/// over the same worlds): the start cells that trap the policy.
fn print_episodes(
    config: &Config,
    task: &TaskConfig,
    episodes: &[((u16, u16), EpisodeMetrics)],
    seed: u64,
) {
    let mut random = PolicySpec::Random
        .build(config, seed, None)
        .expect("the random policy needs no file");
    let floor = evaluate(&config.world, task, random.as_mut(), episodes.len(), seed)
        .ret
        .mean;
    println!("  episode  start     return     AoI  power mW  outages");
    for (i, ((x, y), e)) in episodes.iter().enumerate() {
        let trap = if e.ret < floor { "  trapped" } else { "" };
        println!(
            "  {i:>7}  ({x:>2},{y:>2})  {:>9.1}  {:>6.2}  {:>8.4}  {:>7}{trap}",
            e.ret, e.aoi, e.power_mw, e.outages
        );
    }
    let trapped = episodes.iter().filter(|(_, e)| e.ret < floor).count();
    println!(
        "  trapped   {trapped} of {} episodes below the random policy's mean return ({floor:.1})",
        episodes.len()
    );
}
