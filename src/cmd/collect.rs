//! `uavmeta collect`: one task's offline dataset from a behaviour policy, in one process.

use std::path::PathBuf;

use anyhow::{Context, Result};
use clap::Args;
use indicatif::{ProgressBar, ProgressStyle};
use uavmeta_actors::collect::collect;
use uavmeta_proto::resources::{self, Job};
use uavmeta_world::heuristics::PolicySpec;

use super::common::{ConfigArgs, TaskArgs};

#[derive(Args)]
pub struct CollectArgs {
    #[command(flatten)]
    config: ConfigArgs,
    #[command(flatten)]
    task: TaskArgs,
    /// Behaviour policy: dqn-online | random | stalest | greedy | eps:P | q:P:CHECKPOINT |
    /// actions:FILE [default: collect.policy].
    #[arg(long)]
    policy: Option<PolicySpec>,
    /// Transitions to write [default: collect.transitions].
    #[arg(long, value_parser = clap::builder::RangedU64ValueParser::<usize>::new().range(1..))]
    transitions: Option<usize>,
    /// Seed of the episodes and the policy [default: collect.seed].
    #[arg(long)]
    seed: Option<u64>,
    /// The dataset file; its config is saved beside it as FILE.config.toml.
    #[arg(long)]
    out: PathBuf,
}

pub fn run(args: CollectArgs) -> Result<()> {
    let mut config = args.config.load()?;
    let task = args.task.resolve(&mut config)?;
    // The flags go into the config that is saved beside the dataset, so it alone reproduces it.
    if let Some(policy) = &args.policy {
        config.collect.policy = policy.to_string();
    }
    if let Some(transitions) = args.transitions {
        config.collect.transitions = transitions;
    }
    if let Some(seed) = args.seed {
        config.collect.seed = seed;
    }
    resources::check_memory(&config, Job::Collect)?;
    let key = format!("collect.transitions = {}", config.collect.transitions);
    let dataset = resources::datasets_file_bytes(&config, 1);
    let dir = args.out.parent().unwrap_or(std::path::Path::new("."));
    resources::check_disk(&config, dir, &key, dataset)?;
    if let Some(dir) = args.out.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir)
            .with_context(|| format!("{}: cannot create the directory", dir.display()))?;
    }

    let progress = ProgressBar::no_length().with_style(
        ProgressStyle::with_template("{msg} {bar:40} {pos}/{len} {per_sec} eta {eta}")
            .expect("the template is valid"),
    );
    progress.set_message(format!("{} by {}", task.name, config.collect.policy));
    let summary = collect(&config, &task.name, &args.out, &progress)?;
    progress.finish_and_clear();
    println!(
        "{}: {} transitions of task `{}` by `{}` (seed {}, {} environment steps), {} bytes ({:.1} per transition); config in {}",
        summary.dataset.display(),
        summary.transitions,
        task.name,
        config.collect.policy,
        config.collect.seed,
        summary.steps,
        summary.bytes,
        summary.bytes as f64 / summary.transitions as f64,
        summary.config.display(),
    );
    Ok(())
}
