//! uavmeta's datasets for other offline-RL libraries, and the summary `uavmeta dataset inspect`
//! prints.
//!
//! - [`runs`]: a dataset's transitions regrouped into runs of consecutive steps of one episode,
//!   the episodes both formats store (a dataset sampled from a replay buffer holds fragments).
//! - [`minari`]: Minari's on-disk layout with its Arrow storage, which `minari.load_dataset` opens.
//! - [`npz`]: flat NumPy arrays in the D4RL convention, which d3rlpy's `MDPDataset` takes.
//! - [`inspect`]: a dataset's header, task, counts, return statistics and action histogram.
//!
//! Its main type is [`Export`], built from a file that `uavmeta_proto::dataset::DatasetReader`
//! read and checked (all of it, or N shots drawn by `DatasetReader::shots`, the draw of
//! `uavmeta train --shots`) and the config of the world it was collected in. It only writes files.
//!
//! ```
//! use uavmeta_interop::{npz, Export};
//! use uavmeta_proto::config::Config;
//! use uavmeta_proto::dataset::{DatasetHeader, DatasetReader, DatasetWriter, Transition};
//!
//! let config = Config::from_toml_str("[world]\ndevices = 1", "example.toml", &[]).unwrap();
//! let dir = tempfile::tempdir().unwrap();
//! let file = dir.path().join("lambda-300.uavds");
//! let header = DatasetHeader::for_task(&config, "lambda-300").unwrap();
//! let task = header.task;
//! let step = |t: u32| Transition {
//!     task, actor: 0, episode: 0, step: t, seq: t as u64,
//!     obs: vec![t as u16, 0, t as u16 + 1], action: 2, reward: -1.5,
//!     next_obs: vec![t as u16 + 1, 0, t as u16 + 2], truncated: false,
//! };
//! let mut writer = DatasetWriter::create(&file, header).unwrap();
//! writer.append(&[step(0), step(1)]).unwrap();
//! writer.sync().unwrap();
//!
//! let export = Export::new(&DatasetReader::open(&file).unwrap(), &config, None).unwrap();
//! let written = npz::write(&export, &dir.path().join("lambda-300.npz")).unwrap();
//! // Two consecutive steps are one run: their two rows and one timeout row with the last state.
//! assert_eq!((written.transitions, written.runs, written.rows), (2, 1, 3));
//! ```

pub mod inspect;
pub mod minari;
pub mod npz;
pub mod runs;

use std::path::{Path, PathBuf};

use uavmeta_proto::config::{Config, ConfigError, TaskConfig};
use uavmeta_proto::dataset::{DatasetError, DatasetReader, Transition};
use uavmeta_proto::fs::FileError;

/// Everything an export or an inspection can fail on; each names the file or the value.
#[derive(Debug, thiserror::Error)]
pub enum InteropError {
    #[error(transparent)]
    Dataset(#[from] DatasetError),
    #[error(transparent)]
    Config(#[from] ConfigError),
    #[error("{}: already exists; an export never overwrites, so remove it or choose another output", path.display())]
    Exists { path: PathBuf },
    #[error(transparent)]
    File(#[from] FileError),
    #[error("{}: cannot write the Arrow file", path.display())]
    Arrow {
        path: PathBuf,
        source: arrow_schema::ArrowError,
    },
    #[error("Minari dataset id `{id}`: expected [NAMESPACE/]NAME-vVERSION of letters, digits, `-` and `_`, such as `uavmeta/lambda-300-v0`")]
    BadId { id: String },
    #[error("unknown export format `{found}`: expected `minari` or `npz`")]
    UnknownFormat { found: String },
}

/// The formats `uavmeta dataset export --format` writes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Format {
    /// [`minari`]: a Minari dataset directory.
    Minari,
    /// [`npz`]: one NumPy `.npz` file for d3rlpy.
    Npz,
}

impl std::str::FromStr for Format {
    type Err = InteropError;
    fn from_str(s: &str) -> Result<Self, InteropError> {
        match s {
            "minari" => Ok(Self::Minari),
            "npz" => Ok(Self::Npz),
            _ => Err(InteropError::UnknownFormat { found: s.into() }),
        }
    }
}

/// N shots: how many transitions were drawn from the file, and from which seed.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Shots {
    pub n: usize,
    pub seed: u64,
}

/// One task's transitions to export, in runs of consecutive steps, with where they came from.
pub struct Export<'a> {
    /// The config of the world they were collected in; Minari's metadata holds all of it.
    pub config: &'a Config,
    pub task: TaskConfig,
    /// The dataset file they were read from.
    pub source: PathBuf,
    /// `Some` when they are N shots of the file rather than all of it.
    pub shots: Option<Shots>,
    /// Every exported transition, once, grouped as [`runs::split`] does.
    pub runs: Vec<Vec<Transition>>,
}

impl<'a> Export<'a> {
    /// The file `reader` read, or N shots of it, checked against `config`'s world and task.
    pub fn new(
        reader: &DatasetReader,
        config: &'a Config,
        shots: Option<Shots>,
    ) -> Result<Self, InteropError> {
        reader.check_world(config)?;
        let task = config.task(&reader.header().task_name)?.clone();
        let transitions = match shots {
            Some(Shots { n, seed }) => reader.shots(n, seed)?,
            None => reader.transitions().to_vec(),
        };
        Ok(Self {
            config,
            task,
            source: reader.path().to_path_buf(),
            shots,
            runs: runs::split(transitions),
        })
    }

    pub fn transitions(&self) -> usize {
        self.runs.iter().map(Vec::len).sum()
    }
}

/// Creates the directories above `path` and refuses it if it exists.
fn prepare_output(path: &Path) -> Result<&Path, InteropError> {
    if path.exists() {
        return Err(InteropError::Exists {
            path: path.to_path_buf(),
        });
    }
    let parent = match path.parent() {
        Some(dir) if !dir.as_os_str().is_empty() => dir,
        _ => Path::new("."),
    };
    std::fs::create_dir_all(parent).map_err(FileError::at(parent, "create the directory"))?;
    Ok(parent)
}
