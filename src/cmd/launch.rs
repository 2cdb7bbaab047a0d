//! `uavmeta launch --config F`: a whole run, supervised (see `uavmeta_runtime::launch`); and the
//! `--run DIR` flags every process of a run shares.

use std::io::IsTerminal;
use std::path::PathBuf;

use anyhow::{bail, Context, Result};
use clap::Args;
use indicatif::MultiProgress;
use uavmeta_proto::config::Config;
use uavmeta_proto::resources::{self, Job};
use uavmeta_runtime::launch::Reuse;
use uavmeta_runtime::run_dir::RunDir;

use super::common::ConfigArgs;

/// `--run DIR`, plus the config flags used when the run does not exist yet.
#[derive(Args, Debug)]
pub struct RunArgs {
    /// The run directory. Its `config.toml` (written by `uavmeta launch`, or by the first process
    /// started by hand, from --config and --set) is the config of every process of the run.
    #[arg(long)]
    pub run: PathBuf,
    #[command(flatten)]
    pub config: ConfigArgs,
}

impl RunArgs {
    /// The run directory and its config.
    pub fn open(&self) -> Result<(RunDir, Config)> {
        let run = RunDir::create(&self.run)?;
        if run.config_file().exists() && !self.config.overrides.is_empty() {
            bail!(
                "{}: the run's config is fixed when the run starts; --set {} cannot change it",
                run.config_file().display(),
                self.config.overrides.join(" --set ")
            );
        }
        let config =
            run.load_or_init_config(|| Config::load(&self.config.config, &self.config.overrides))?;
        config.require_one_uav("a launch")?;
        Ok((run, config))
    }

    /// `process` (the store, the meta-learner, the evaluator) on the run directory and its config.
    /// Runs `process`, the run's `job`, once its memory is checked.
    pub fn serve<T, E>(&self, job: Job, process: fn(&RunDir, &Config) -> Result<T, E>) -> Result<()>
    where
        E: std::error::Error + Send + Sync + 'static,
    {
        let (run, config) = self.open()?;
        resources::check_memory(&config, job)?;
        process(&run, &config)?;
        Ok(())
    }
}

#[derive(Args, Debug)]
pub struct LaunchArgs {
    #[command(flatten)]
    pub config: ConfigArgs,
    /// Continue the run in run.dir, which must exist and have been made with this config (the
    /// default also continues a run of the same config, and starts one where there is none).
    #[arg(long, conflicts_with = "fresh")]
    pub resume: bool,
    /// Move a run already in run.dir aside (to `<dir>.moved-N`) and start afresh.
    #[arg(long)]
    pub fresh: bool,
}

/// `terminal`: the rows on stderr that the log lines go through (`main`), where the run is shown
/// when stderr is a terminal.
pub fn run(args: LaunchArgs, terminal: MultiProgress) -> Result<()> {
    let config = args.config.load()?;
    let exe = std::env::current_exe()
        .context("cannot find the uavmeta binary to start the run's processes")?;
    let terminal = std::io::stderr().is_terminal().then_some(&terminal);
    let reuse = match (args.resume, args.fresh) {
        (true, _) => Reuse::Resume,
        (_, true) => Reuse::Fresh,
        _ => Reuse::IfSame,
    };
    let report = uavmeta_runtime::launch::launch_seeds(exe, &config, reuse, terminal)?;
    if report.seeds.len() > 1 {
        for (seed, r) in &report.seeds {
            println!("seed {seed}:");
            print!("{}", uavmeta_runtime::launch::results_table(r));
        }
        println!(
            "\nover seeds {:?} (learned rows: mean ± 95% interval over the seeds):",
            config.run.seeds
        );
    }
    print!(
        "{}",
        uavmeta_runtime::launch::results_table(&report.aggregate)
    );
    Ok(())
}
