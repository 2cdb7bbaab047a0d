//! `uavmeta actor --run R --task T [--policy P] [--seed S] [--transitions N]`: one actor of a run
//! (see `uavmeta_runtime::actor`).

use anyhow::{Context, Result};
use clap::Args;
use uavmeta_proto::resources::{self, Job};
use uavmeta_runtime::actor::{self, ActorOptions};
use uavmeta_world::heuristics::PolicySpec;

use super::launch::RunArgs;

#[derive(Args, Debug)]
pub struct ActorArgs {
    #[command(flatten)]
    pub run: RunArgs,
    /// The task to act in, named in the run's config.
    #[arg(long)]
    pub task: String,
    /// Behaviour policy: dqn-online, random, stalest, greedy, eps:P, q:P:CHECKPOINT or
    /// actions:FILE; default `collect.policy`.
    #[arg(long)]
    pub policy: Option<String>,
    /// Seed of the episodes and the policy; default `collect.seed`. Actors of one task with
    /// different seeds add different data; the same seed makes the same transitions, kept once.
    #[arg(long)]
    pub seed: Option<u64>,
    /// Stop after publishing this many transitions (default: until the dataset is complete).
    #[arg(long)]
    pub transitions: Option<u64>,
}

pub fn run(args: ActorArgs) -> Result<()> {
    let (run, config) = args.run.open()?;
    let spec = args.policy.as_deref().unwrap_or(&config.collect.policy);
    let policy: PolicySpec = spec.parse().with_context(|| format!("--policy {spec}"))?;
    let mut acting = config.clone();
    acting.collect.policy = policy.to_string();
    resources::check_memory(&acting, Job::Collect)?;
    let options = ActorOptions {
        task: args.task,
        policy,
        seed: args.seed.unwrap_or(config.collect.seed),
        transitions: args.transitions,
    };
    actor::run(&run, &config, &options)?;
    Ok(())
}
