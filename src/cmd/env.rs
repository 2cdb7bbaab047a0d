//! `uavmeta env`: look at the world through a policy's episodes.

use std::io::{self, Write};

use anyhow::{Context, Result};
use clap::{Args, Subcommand};
use serde::Serialize;
use uavmeta_proto::resources::{self, Job};
use uavmeta_proto::stats::{EpisodeMetrics, PolicyMetrics};
use uavmeta_world::heuristics::PolicySpec;
use uavmeta_world::rollout::{episode_worlds, evaluation_worlds, run_worlds, StepRecord};

use super::common::{ConfigArgs, TaskArgs};

#[derive(Subcommand)]
pub enum EnvCommand {
    /// Roll out a policy and print each episode's return, AoI, power and outages with their means.
    Rollout(RolloutArgs),
}

#[derive(Args)]
pub struct RolloutArgs {
    #[command(flatten)]
    config: ConfigArgs,
    #[command(flatten)]
    task: TaskArgs,
    /// random | stalest | greedy | planner | eps:P | q:P:CHECKPOINT (a saved Q-network's greedy
    /// policy, uniform random with probability P) | actions:FILE (one action index per line,
    /// replayed across episodes).
    #[arg(long, default_value = "stalest")]
    policy: PolicySpec,
    /// Monte-Carlo episodes.
    #[arg(long, default_value_t = 20)]
    episodes: usize,
    /// Evaluate exactly as the tables do: one episode from every start cell where the world is
    /// deterministic (no moving rain), `--episodes` Monte-Carlo episodes where it is not.
    #[arg(long)]
    exact: bool,
    /// Seed of the episodes (start cells, rain moves) and of the policy's own randomness.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Print one JSON object per step on stdout; the table then goes to stderr.
    #[arg(long)]
    trace: bool,
    /// Print the summary as JSON on stdout instead of a table.
    #[arg(long)]
    json: bool,
}

pub fn run(command: EnvCommand) -> Result<()> {
    match command {
        EnvCommand::Rollout(args) => run_rollout(args),
    }
}

/// A step of `--trace`, tagged with its episode.
#[derive(Serialize)]
struct TraceLine<'a> {
    episode: usize,
    #[serde(flatten)]
    step: &'a StepRecord<'a>,
}

/// What `--json` prints.
#[derive(Serialize)]
struct Summary<'a> {
    config: &'a str,
    task: &'a str,
    lambda: f64,
    policy: String,
    seed: u64,
    episodes: &'a [EpisodeMetrics],
    mean: PolicyMetrics,
}

fn run_rollout(args: RolloutArgs) -> Result<()> {
    anyhow::ensure!(
        args.episodes > 0,
        "--episodes {}: expected at least 1 episode",
        args.episodes
    );
    let mut config = args.config.load_team()?;
    let task = args.task.resolve(&mut config)?;
    let spec = &args.policy;
    let job = match spec {
        PolicySpec::Planner => Job::Plan,
        _ => Job::Eval,
    };
    let worlds = resources::evaluation_worlds(&config, &task, args.episodes, args.exact);
    let flag = format!("--episodes = {}", args.episodes);
    resources::check_memory_with_episodes(&config, job, flag, worlds)?;
    let steps = args.episodes.saturating_mul(config.world.horizon as usize);
    let mut policy = uavmeta_actors::policy::build(spec, &config, args.seed, Some(steps))?;

    let stdout = io::stdout();
    let mut out = io::BufWriter::new(stdout.lock());
    let mut trace_error = None;
    let worlds = match args.exact {
        true => evaluation_worlds(&config.world, &task, args.episodes, args.seed),
        false => episode_worlds(&config.world, &task, args.episodes, args.seed).collect(),
    };
    let count = worlds.len();
    let episodes = run_worlds(worlds, policy.as_mut(), |episode, step| {
        if args.trace && trace_error.is_none() {
            let line = TraceLine { episode, step };
            if let Err(e) = serde_json::to_writer(&mut out, &line)
                .map_err(io::Error::from)
                .and_then(|()| writeln!(out))
            {
                trace_error = Some(e);
            }
        }
    });
    if let Some(e) = trace_error {
        return Err(e).context("writing the trace");
    }
    let mean = PolicyMetrics::from_episodes(&episodes);

    if args.json {
        let summary = Summary {
            config: &config.origin,
            task: &task.name,
            lambda: task.lambda,
            policy: spec.to_string(),
            seed: args.seed,
            episodes: &episodes,
            mean,
        };
        serde_json::to_writer(&mut out, &summary)?;
        writeln!(out)?;
    } else {
        let header = format!(
            "{} on task {} (lambda = {}), seed {}, {} episodes of {} steps",
            spec, task.name, task.lambda, args.seed, count, config.world.horizon
        );
        let table = table(&header, &episodes, &mean);
        if args.trace {
            out.flush()?;
            eprint!("{table}");
        } else {
            write!(out, "{table}")?;
        }
    }
    out.flush()?;
    Ok(())
}

/// The per-episode rows and the means with their 95% confidence half-widths.
fn table(header: &str, episodes: &[EpisodeMetrics], mean: &PolicyMetrics) -> String {
    let mut s = format!(
        "{header}\n{:>8} {:>12} {:>9} {:>11} {:>8}\n",
        "episode", "return", "AoI", "power mW", "outages"
    );
    for (i, e) in episodes.iter().enumerate() {
        s += &format!(
            "{:>8} {:>12.2} {:>9.3} {:>11.4} {:>8}\n",
            i, e.ret, e.aoi, e.power_mw, e.outages
        );
    }
    s += &format!(
        "mean ± 95% CI: return {:.2}, AoI {:.3}, power {:.4} mW, outages {:.2}\n",
        mean.ret, mean.aoi, mean.power_mw, mean.outages
    );
    s
}
