//! `uavmeta dataset export` and `uavmeta dataset inspect`: a dataset file for Minari and d3rlpy
//! users, and a summary of one.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result};
use clap::{Args, Subcommand};
use uavmeta_actors::collect::config_path;
use uavmeta_interop::inspect::Summary;
use uavmeta_interop::{minari, npz, Export, Format, Shots};
use uavmeta_proto::config::Config;
use uavmeta_proto::dataset::DatasetReader;

#[derive(Subcommand)]
pub enum DatasetCommand {
    /// Write a dataset, or N shots of it, as a Minari dataset or a NumPy .npz for d3rlpy.
    Export(ExportArgs),
    /// Print a dataset's header, task, transitions, episodes, returns and action histogram,
    /// checking every CRC32.
    Inspect(InspectArgs),
}

#[derive(Args)]
pub struct ExportArgs {
    /// The dataset file (.uavds).
    #[arg(long)]
    dataset: PathBuf,
    /// The config it was collected with [default: FILE.config.toml, which `uavmeta collect`
    /// saves beside it; a run's datasets take the run's config.toml].
    #[arg(long)]
    config: Option<PathBuf>,
    /// minari (a Minari dataset, Arrow storage) or npz (flat arrays for d3rlpy's MDPDataset).
    #[arg(long, value_parser = |s: &str| s.parse::<Format>())]
    format: Format,
    /// npz: the file to write. minari: the datasets root (what MINARI_DATASETS_PATH names) to
    /// write ID/data under.
    #[arg(long)]
    out: PathBuf,
    /// The Minari dataset id [default: uavmeta/TASK-v0, or uavmeta/TASK-Nshots-v0 with --shots].
    #[arg(long)]
    id: Option<String>,
    /// Export N shots instead of the whole file: the draw `uavmeta train --shots N` makes.
    #[arg(long, value_parser = clap::builder::RangedU64ValueParser::<usize>::new().range(1..))]
    shots: Option<usize>,
    /// Seed of the shot draw [default: run.seeds[0], as for train].
    #[arg(long, requires = "shots")]
    seed: Option<u64>,
    /// minari: write the observations normalised (x/(L-1), y/(L-1), A/aoi_max), as the networks
    /// and the Python env's `normalised=True` see them, instead of raw.
    #[arg(long)]
    normalised: bool,
}

#[derive(Args)]
pub struct InspectArgs {
    /// The dataset file (.uavds).
    dataset: PathBuf,
    /// The config it was collected with, for the task's lambda and rain and the store's checks of
    /// every transition [default: FILE.config.toml, or the run's config.toml for a file in a
    /// run's datasets/, when it exists].
    #[arg(long)]
    config: Option<PathBuf>,
}

pub fn run(command: DatasetCommand) -> Result<()> {
    match command {
        DatasetCommand::Export(args) => export(args),
        DatasetCommand::Inspect(args) => inspect(args),
    }
}

fn export(args: ExportArgs) -> Result<()> {
    if args.id.is_some() && args.format != Format::Minari {
        anyhow::bail!("--id names a Minari dataset; --format npz writes the one file --out names");
    }
    if args.normalised && args.format != Format::Minari {
        anyhow::bail!("--normalised applies to --format minari; npz keeps the raw observations");
    }
    // The dataset first: a mistyped dataset path is reported as that, not as a missing config.
    let reader = DatasetReader::open(&args.dataset)?;
    let config_file = args
        .config
        .or_else(|| saved_config_path(&args.dataset))
        .unwrap_or_else(|| config_path(&args.dataset));
    let config = Config::load(&config_file, &[]).with_context(|| {
        format!(
            "{}: the dataset's config; pass --config FILE, the config it was collected with",
            args.dataset.display()
        )
    })?;
    let shots = match args.shots {
        Some(n) => Some(Shots {
            n,
            seed: args.seed.unwrap_or(config.run.seeds[0]),
        }),
        None => None,
    };
    let export = Export::new(&reader, &config, shots)?;
    match args.format {
        Format::Npz => {
            let written = npz::write(&export, &args.out)?;
            println!(
                "{}: {} transitions of task `{}` in {} runs of consecutive steps, {} rows (a timeout row ends each run)",
                args.out.display(),
                written.transitions,
                export.task.name,
                written.runs,
                written.rows
            );
        }
        Format::Minari => {
            let id = args
                .id
                .unwrap_or_else(|| minari::default_id(&export.task.name, shots));
            let observations = match args.normalised {
                true => minari::Observations::Normalised,
                false => minari::Observations::Raw,
            };
            let written = minari::write(&export, &args.out, &id, observations)?;
            println!(
                "{}: Minari dataset `{id}`, {} steps of task `{}` in {} episodes; load it with MINARI_DATASETS_PATH={}",
                written.dir.display(),
                written.steps,
                export.task.name,
                written.episodes,
                args.out.display()
            );
        }
    }
    Ok(())
}

fn inspect(args: InspectArgs) -> Result<()> {
    let reader = DatasetReader::open(&args.dataset)?;
    let config = match args.config {
        Some(file) => Some(Config::load(&file, &[])?),
        None => saved_config(&args.dataset)?,
    };
    let summary = Summary::new(&reader, config.as_ref())?;
    print!("{summary}");
    match summary.validation.as_ref().and_then(|v| v.first.as_ref()) {
        Some((index, rejection)) => anyhow::bail!(
            "{}: {} transitions fail the store's checks; the first, transition {index}: {rejection}",
            args.dataset.display(),
            summary.validation.as_ref().map_or(0, |v| v.failures()),
        ),
        None => Ok(()),
    }
}

/// The config `uavmeta collect` saved beside `dataset`, or the config of the run whose
/// `datasets/` holds it, if there is one.
fn saved_config(dataset: &Path) -> Result<Option<Config>> {
    match saved_config_path(dataset) {
        Some(file) => Ok(Some(Config::load(&file, &[])?)),
        None => Ok(None),
    }
}

/// Where [`saved_config`] finds the dataset's config: FILE.config.toml beside it, else the
/// `config.toml` of the run whose `datasets/` holds it; `None` if neither exists.
fn saved_config_path(dataset: &Path) -> Option<PathBuf> {
    let beside = config_path(dataset);
    let in_run = dataset
        .parent()
        .filter(|dir| dir.file_name().is_some_and(|name| name == "datasets"))
        .and_then(Path::parent)
        .map(|run| run.join("config.toml"));
    std::iter::once(beside)
        .chain(in_run)
        .find(|file| file.exists())
}
