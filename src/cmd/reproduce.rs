//! `uavmeta reproduce`: the paper's figures 4-9 over several seeds, beside its claims.

use std::io::IsTerminal;
use std::path::{Path, PathBuf};
use std::process::Command;

use anyhow::{Context, Result};
use clap::builder::PossibleValuesParser;
use clap::Args;
use indicatif::{ProgressBar, ProgressStyle};
use uavmeta_reproduce::{
    self as reproduce, quick_config, Experiment, JobSelector, Kind, ReproduceConfig,
    ReproduceOptions,
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
    /// Where the plan's jobs run: this machine's pool, or a Slurm cluster (one sbatch job array
    /// per kind of job; OUT on a filesystem every node sees; docs/REPRODUCING.md).
    #[arg(long, default_value = "local", value_parser = ["local", "slurm"])]
    engine: String,
    /// Print which jobs of the plan in OUT are done, running (as squeue says) and left, with an
    /// estimate of the time left; reads OUT only (no --config needed).
    #[arg(long, conflicts_with_all = ["job", "stage"])]
    status: bool,
    /// With --status: redraw a progress bar until every job is done or none is queued.
    #[arg(long, requires = "status")]
    watch: bool,
    /// Run one job of the plan OUT/plan.json holds, by its id (written with the same options).
    #[arg(long, value_name = "ID", conflicts_with = "stage")]
    job: Option<String>,
    /// Run the job of this kind at --index (how a Slurm array's task picks its job).
    #[arg(long, value_name = "KIND", requires = "index", value_parser = PossibleValuesParser::new(Kind::ALL.map(Kind::name)))]
    stage: Option<String>,
    /// The job's position among its kind's jobs in OUT/plan.json.
    #[arg(long, value_name = "N", requires = "stage", hide = true)]
    index: Option<usize>,
    /// --engine slurm: sbatch --partition [default: reproduce.slurm.partition].
    #[arg(long)]
    partition: Option<String>,
    /// --engine slurm: sbatch --account [default: reproduce.slurm.account].
    #[arg(long)]
    account: Option<String>,
    /// --engine slurm: sbatch --time of every job [default: reproduce.slurm.time].
    #[arg(long)]
    time: Option<String>,
    /// --engine slurm: sbatch --cpus-per-task [default: reproduce.slurm.cpus_per_task].
    #[arg(long, value_name = "N")]
    cpus_per_task: Option<usize>,
    /// --engine slurm: one more sbatch option, repeatable (`--sbatch-arg=--mem=4G`)
    /// [default: reproduce.slurm.sbatch_args].
    #[arg(long = "sbatch-arg", value_name = "OPTION", allow_hyphen_values = true)]
    sbatch_args: Vec<String>,
}

pub fn run(args: ReproduceArgs) -> Result<()> {
    let out = args.out.clone().unwrap_or_else(|| {
        PathBuf::from(if args.quick {
            "runs/reproduce-quick"
        } else {
            "runs/reproduce"
        })
    });
    if args.status {
        return status(&out, args.watch);
    }
    let job_command = job_command(&args, &out)?;
    let mut config = ConfigArgs {
        config: args.config,
        overrides: args.overrides,
    }
    .load()?;
    if args.quick {
        config = quick_config(&config)?;
    }
    {
        let mut r: ReproduceConfig = config.reproduce.read(&config.origin)?;
        r.seeds = args.seeds.unwrap_or(r.seeds);
        let s = &mut r.slurm;
        s.partition = args.partition.unwrap_or(s.partition.clone());
        s.account = args.account.unwrap_or(s.account.clone());
        s.time = args.time.unwrap_or(s.time.clone());
        s.cpus_per_task = args.cpus_per_task.unwrap_or(s.cpus_per_task);
        if !args.sbatch_args.is_empty() {
            s.sbatch_args = args.sbatch_args;
        }
        r.write_into(&mut config);
    }
    let experiments =
        Experiment::select(&args.experiment).expect("clap admits only Experiment::CHOICES");
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
    let opts = ReproduceOptions {
        config: &config,
        experiments: &experiments,
        quick: args.quick,
        out_dir: &out,
        jobs,
        progress: std::io::stderr().is_terminal(),
        command: &command,
        commit: &commit(),
    };
    let selected = match (args.job, args.stage, args.index) {
        (Some(id), _, _) => Some(JobSelector::Id(id)),
        (None, Some(kind), Some(index)) => Some(JobSelector::Index(
            Kind::parse(&kind).expect("clap admits only the kinds"),
            index,
        )),
        _ => None,
    };
    if let Some(job) = selected {
        if let Some(report) = reproduce::run_job(&opts, &job)? {
            println!("written: {}", report.summary_path.display());
        }
        return Ok(());
    }
    if args.engine == "slurm" {
        let submitted = reproduce::submit(&opts, &job_command)?;
        print!("{}", submitted.describe(&out));
        return Ok(());
    }
    let report = reproduce::run(&opts)?;
    print!("{}", report.summary);
    println!(
        "\nwritten: {} ({:.1} min)",
        report.summary_path.display(),
        report.wall.as_secs_f64() / 60.0
    );
    Ok(())
}

/// The command a Slurm job runs: this binary with every option that decides the plan, absolute
/// paths, so `--stage KIND --index N` after it runs that job wherever the cluster starts it.
fn job_command(args: &ReproduceArgs, out: &Path) -> Result<Vec<String>> {
    let absolute = |p: &Path| -> Result<String> {
        let p = std::path::absolute(p).with_context(|| format!("{}", p.display()))?;
        Ok(p.display().to_string())
    };
    let binary = std::env::current_exe().context("the path of this binary")?;
    let mut command = vec![absolute(&binary)?, "reproduce".into()];
    command.extend(["--config".into(), absolute(&args.config)?]);
    for set in &args.overrides {
        command.extend(["--set".into(), set.clone()]);
    }
    command.extend(["--experiment".into(), args.experiment.clone()]);
    if let Some(seeds) = args.seeds {
        command.extend(["--seeds".into(), seeds.to_string()]);
    }
    if args.quick {
        command.push("--quick".into());
    }
    command.extend(["--out".into(), absolute(out)?]);
    Ok(command)
}

/// `--status`: the plan in `out`, once or (`watch`) as a progress bar until it ends.
fn status(out: &Path, watch: bool) -> Result<()> {
    let status = reproduce::status::status(out)?;
    if !watch {
        print!("{}", status.describe());
        return Ok(());
    }
    let bar = ProgressBar::new(status.total as u64).with_style(
        ProgressStyle::with_template("{bar:40} {pos}/{len} jobs {msg}")
            .expect("the template is valid"),
    );
    loop {
        let status = reproduce::status::status(out)?;
        bar.set_position(status.done as u64);
        let running = status.running.as_ref().map_or(0, Vec::len);
        bar.set_message(format!("({running} running; {})", status.eta_text()));
        if status.finished() || status.queued == Some(0) {
            bar.finish();
            print!("{}", status.describe());
            return Ok(());
        }
        std::thread::sleep(std::time::Duration::from_secs(2));
    }
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
