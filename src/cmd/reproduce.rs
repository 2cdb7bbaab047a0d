//! `uavmeta reproduce`: the paper's figures 4-9 over several seeds, beside its claims.

use std::io::IsTerminal;
use std::path::PathBuf;
use std::process::Command;

use anyhow::Result;
use clap::builder::PossibleValuesParser;
use clap::Args;
use uavmeta_reproduce::{
    self as reproduce, quick_config, Experiment, ReproduceConfig, ReproduceOptions,
};

use super::common::ConfigArgs;

#[derive(Args)]
pub struct ReproduceArgs {
    /// Experiment config (TOML, docs/MODEL.md section 7); its `[reproduce]` section sizes the
    /// experiments.
    #[arg(long, default_value = "configs/reproduce.toml")]
    config: PathBuf,
    /// Override one key, dotted as in the file: `--set reproduce.seeds=3`.
    #[arg(long = "set", value_name = "KEY=VALUE")]
    overrides: Vec<String>,
    /// The experiment (figure) to run, or all of them.
    #[arg(long, default_value = "all", value_parser = PossibleValuesParser::new(Experiment::CHOICES))]
    experiment: String,
    /// Seeds 0..N-1 [default: reproduce.seeds].
    #[arg(long, value_name = "N", value_parser = clap::builder::RangedU64ValueParser::<usize>::new().range(1..=1000))]
    seeds: Option<usize>,
    /// The whole pipeline at tiny sizes (about 20 s on two cores): checks plumbing, not the claims.
    #[arg(long)]
    quick: bool,
    /// Output directory: one directory per experiment, summary.md, and cache/ (datasets, agents,
    /// w0s reused by later runs with the same config) [default: runs/reproduce, or
    /// runs/reproduce-quick with --quick].
    #[arg(long)]
    out: Option<PathBuf>,
    /// Worker threads: datasets, inits and fine-tuning runs of any seed run this many at a time,
    /// one libtorch thread each [default: the available cores].
    #[arg(long, value_name = "J", value_parser = clap::builder::RangedU64ValueParser::<usize>::new().range(1..=256))]
    jobs: Option<usize>,
}

pub fn run(args: ReproduceArgs) -> Result<()> {
    let mut config = ConfigArgs {
        config: args.config,
        overrides: args.overrides,
    }
    .load()?;
    if args.quick {
        config = quick_config(&config)?;
    }
    if let Some(seeds) = args.seeds {
        let mut r: ReproduceConfig = config.reproduce.read(&config.origin)?;
        r.seeds = seeds;
        r.write_into(&mut config);
    }
    let experiments =
        Experiment::select(&args.experiment).expect("clap admits only Experiment::CHOICES");
    let out = args.out.unwrap_or_else(|| {
        PathBuf::from(if args.quick {
            "runs/reproduce-quick"
        } else {
            "runs/reproduce"
        })
    });
    let jobs = args
        .jobs
        .unwrap_or_else(|| std::thread::available_parallelism().map_or(1, |n| n.get()));
    let command = std::env::args()
        .map(|a| {
            if a.contains(char::is_whitespace) {
                format!("'{a}'")
            } else {
                a
            }
        })
        .collect::<Vec<_>>()
        .join(" ");
    let report = reproduce::run(&ReproduceOptions {
        config: &config,
        experiments: &experiments,
        quick: args.quick,
        out_dir: &out,
        jobs,
        progress: std::io::stderr().is_terminal(),
        command: &command,
        commit: &commit(),
    })?;
    print!("{}", report.summary);
    println!(
        "\nwritten: {} ({:.1} min)",
        report.summary_path.display(),
        report.wall.as_secs_f64() / 60.0
    );
    Ok(())
}

/// The git commit of the working tree, marked when it has uncommitted changes; "unknown" outside
/// a git checkout.
fn commit() -> String {
    let git = |args: &[&str]| {
        Command::new("git")
            .args(args)
            .output()
            .ok()
            .filter(|o| o.status.success())
            .map(|o| String::from_utf8_lossy(&o.stdout).trim().to_string())
    };
    match git(&["rev-parse", "--short", "HEAD"]) {
        Some(hash) if !hash.is_empty() => {
            let dirty = git(&["status", "--porcelain", "--untracked-files=no"])
                .is_some_and(|s| !s.is_empty());
            if dirty {
                format!("{hash} (with uncommitted changes)")
            } else {
                hash
            }
        }
        _ => "unknown".into(),
    }
}
