//! Minari's on-disk dataset layout with its Arrow storage (minari 0.5,
//! `minari/dataset/_storages/arrow_storage.py`), which `minari.load_dataset(ID)` opens when
//! `MINARI_DATASETS_PATH` is the root it was written under:
//!
//! ```text
//! ROOT/ID/data/metadata.json        the dataset: id, counts, spaces, format, task, lambda, rain, config,
//!                                   whether the observations are normalised and by what scale
//! ROOT/ID/data/<i>/part-0.arrow     episode i: one Arrow IPC record batch
//! ROOT/ID/data/<i>/metadata.json    its id and steps, and the actor, episode and first step it comes from
//! ```
//!
//! **Why Arrow.** Minari reads HDF5, Arrow IPC and Parquet. HDF5 needs the C library (Debian's
//! libhdf5-dev) to build and to run every uavmeta binary; Parquet's crate brings a Thrift codec
//! and compression codecs that episodes of a hundred rows do not need; the Arrow IPC crates are
//! pure Rust and a few small crates. Reading it takes pyarrow on the Python side
//! (`pip install "minari[arrow]"`).
//!
//! **Episodes.** Each run of consecutive steps ([`crate::runs`]) is an episode.
//! `observations` hold its n steps' observations and the final next observation (n + 1 rows,
//! raw float32 values as in the dataset file, or with [`Observations::Normalised`] divided by
//! L-1, L-1 and aoi_max bit for bit as the Python env's `normalised=True` gives them); `actions`, `rewards`, `terminations` and
//! `truncations` hold n values, padded by one row as Minari's own writer does (its reader drops
//! that row). Terminations are all false, since the world has no terminal state; a truncation
//! marks the step that reached the horizon. A run that the sampling cut short ends with neither:
//! its next step is simply not in the data.

use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::Path;
use std::sync::Arc;

use arrow_array::{
    ArrayRef, BooleanArray, FixedSizeListArray, Float32Array, Int64Array, RecordBatch,
};
use arrow_ipc::writer::FileWriter;
use arrow_schema::{ArrowError, DataType, Field};
use serde_json::{json, Value};
use uavmeta_proto::config::WorldConfig;
use uavmeta_proto::dataset::Transition;
use uavmeta_proto::fs::FileError;

use crate::{prepare_output, Export, InteropError, Shots};

/// The Minari release whose layout this writes; every later 0.5 release reads it.
pub const MINARI_VERSION: &str = "0.5.4";

/// The name pyarrow's `write_dataset` gives the one file of a partition.
const EPISODE_FILE: &str = "part-0.arrow";

/// How the observations are written.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Observations {
    /// As the dataset file holds them: [x, y, A_1..A_K] as float32 integers.
    #[default]
    Raw,
    /// x/(L-1), y/(L-1), A/aoi_max: what the networks and `uavmeta.UavEnv(normalised=True)` see.
    Normalised,
}

/// What [`write`] wrote.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct MinariSummary {
    /// `ROOT/ID`, the dataset's directory.
    pub dir: std::path::PathBuf,
    pub episodes: usize,
    pub steps: usize,
}

/// `uavmeta/<task>-v0`, or `uavmeta/<task>-<N>shots-v0`, with every character Minari's ids do
/// not allow (such as the dot of `lambda-12.5`) replaced by `_`.
pub fn default_id(task_name: &str, shots: Option<Shots>) -> String {
    let name: String = task_name
        .chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || c == '-' {
                c
            } else {
                '_'
            }
        })
        .collect();
    match shots {
        Some(Shots { n, .. }) => format!("uavmeta/{name}-{n}shots-v0"),
        None => format!("uavmeta/{name}-v0"),
    }
}

/// Minari's `DATASET_ID_RE`: `[namespace/]name-vN`, of word characters and `-`, no empty parts.
fn check_id(id: &str) -> Result<(), InteropError> {
    let word = |part: &str| {
        !part.is_empty()
            && part
                .chars()
                .all(|c| c.is_ascii_alphanumeric() || c == '-' || c == '_')
    };
    let (path, version) = id.rsplit_once("-v").unwrap_or((id, ""));
    let valid = path.split('/').all(word)
        && !version.is_empty()
        && version.chars().all(|c| c.is_ascii_digit());
    match valid {
        true => Ok(()),
        false => Err(InteropError::BadId { id: id.into() }),
    }
}

/// Writes `export` as Minari dataset `id` under `root`, the observations as `observations` says.
/// The dataset appears whole or not at all: it is written beside its place under a hidden name,
/// which Minari's listing skips, and renamed.
pub fn write(
    export: &Export,
    root: &Path,
    id: &str,
    observations: Observations,
) -> Result<MinariSummary, InteropError> {
    check_id(id)?;
    let dir = root.join(id);
    let parent = prepare_output(&dir)?;
    let staging = tempfile::Builder::new()
        .prefix(".uavmeta-export")
        .tempdir_in(parent)
        .map_err(FileError::at(parent, "create a directory in"))?;
    let data = staging.path().join("data");
    let mut bytes = 0;
    for (i, run) in export.runs.iter().enumerate() {
        bytes += write_episode(
            &data.join(i.to_string()),
            i,
            run,
            &export.config.world,
            observations,
        )?;
    }
    let metadata = dataset_metadata(export, id, bytes, observations);
    write_json(&data.join("metadata.json"), &metadata)?;
    // Dropping `staging` after the rename finds nothing left to remove.
    std::fs::rename(staging.path(), &dir).map_err(FileError::at(&dir, "create"))?;
    Ok(MinariSummary {
        dir,
        episodes: export.runs.len(),
        steps: export.transitions(),
    })
}

/// Episode `id`'s directory: its Arrow file and its metadata. Returns the Arrow file's size.
fn write_episode(
    dir: &Path,
    id: usize,
    run: &[Transition],
    world: &WorldConfig,
    observations: Observations,
) -> Result<u64, InteropError> {
    std::fs::create_dir_all(dir).map_err(FileError::at(dir, "create the directory"))?;
    let path = dir.join(EPISODE_FILE);
    let arrow = |source| InteropError::Arrow {
        path: path.clone(),
        source,
    };
    let batch = episode_batch(run, &scale_of(world, observations)).map_err(arrow)?;
    let file = File::create(&path).map_err(FileError::at(&path, "create"))?;
    let mut writer = FileWriter::try_new(BufWriter::new(file), &batch.schema()).map_err(arrow)?;
    writer.write(&batch).map_err(arrow)?;
    writer.finish().map_err(arrow)?;
    writer
        .into_inner()
        .map_err(arrow)?
        .flush()
        .map_err(FileError::at(&path, "write"))?;
    let first = &run[0];
    write_json(
        &dir.join("metadata.json"),
        &json!({
            "id": id,
            "total_steps": run.len(),
            "actor": first.actor,
            "episode": first.episode,
            "first_step": first.step,
        }),
    )?;
    let size = std::fs::metadata(&path).map_err(FileError::at(&path, "stat"))?;
    Ok(size.len())
}

/// What each observation entry is multiplied by: 1, or the f32 reciprocal of its scale, as
/// `World::write_normalised` computes it.
fn scale_of(world: &WorldConfig, observations: Observations) -> Vec<f32> {
    match observations {
        Observations::Raw => vec![1.0; world.layout().observation_len()],
        Observations::Normalised => world.observation_scale().iter().map(|s| 1.0 / s).collect(),
    }
}

/// One episode's columns, each padded to the n + 1 rows of its observations, which are
/// multiplied entry by entry by `inv_scale`.
fn episode_batch(run: &[Transition], inv_scale: &[f32]) -> Result<RecordBatch, ArrowError> {
    let observation_len = inv_scale.len();
    let last = run.last().expect("a run is never empty");
    let observations: Float32Array = run
        .iter()
        .map(|t| &t.obs)
        .chain([&last.next_obs])
        .flat_map(|obs| obs.iter().zip(inv_scale))
        .map(|(&v, &inv)| Some(f32::from(v) * inv))
        .collect();
    // pyarrow's `pa.list_(pa.float32(), list_size=n)`, as Minari encodes a Box space.
    let item = Arc::new(Field::new("item", DataType::Float32, true));
    let width = i32::try_from(observation_len).expect("2 + K is small");
    let observations = FixedSizeListArray::try_new(item, width, Arc::new(observations), None)?;
    let actions = Int64Array::from_iter_values(run.iter().map(|t| i64::from(t.action)).chain([0]));
    let rewards = Float32Array::from_iter_values(run.iter().map(|t| t.reward).chain([0.0]));
    let terminations = BooleanArray::from(vec![false; run.len() + 1]);
    let truncations: BooleanArray = run
        .iter()
        .map(|t| Some(t.truncated))
        .chain([Some(false)])
        .collect();
    RecordBatch::try_from_iter([
        ("observations", Arc::new(observations) as ArrayRef),
        ("actions", Arc::new(actions)),
        ("rewards", Arc::new(rewards)),
        ("terminations", Arc::new(terminations)),
        ("truncations", Arc::new(truncations)),
    ])
}

/// The dataset's `metadata.json`: Minari's keys, then what uavmeta knows of the data.
fn dataset_metadata(export: &Export, id: &str, bytes: u64, observations: Observations) -> Value {
    let world = &export.config.world;
    let action_space = json!({
        "type": "Discrete", "dtype": "int64", "start": 0, "n": world.layout().action_count(),
    });
    json!({
        "dataset_id": id,
        "total_episodes": export.runs.len(),
        "total_steps": export.transitions(),
        "data_format": "arrow",
        "jpeg_encoding": false,
        // Minari stores spaces as JSON strings inside the JSON.
        "observation_space": observation_space(world, observations).to_string(),
        "action_space": action_space.to_string(),
        "minari_version": MINARI_VERSION,
        // In MB with one decimal, as `minari list local` shows it.
        "dataset_size": (bytes as f64 / 1e5).round() / 10.0,
        "algorithm_name": export.config.collect.policy,
        "description": format!(
            "uavmeta task `{}`: UAV trajectory and scheduling with {} devices, lambda = {}",
            export.task.name, world.devices, export.task.lambda
        ),
        "task": export.task.name,
        "lambda": export.task.lambda,
        "rain": export.task.rain,
        "rain_moves_every": export.task.rain_moves_every,
        "task_id": export.config.tasks.iter().position(|t| t.name == export.task.name),
        "role": export.task.role,
        "normalised": observations == Observations::Normalised,
        "observation_scale": world.observation_scale(),
        // The horizon is a time limit: `terminations` are all false, `truncations` mark it.
        "horizon": world.horizon,
        "config": export.config.to_toml_string(),
        "source": export.source.display().to_string(),
        "shots": export.shots.map(|s| s.n),
        "shots_seed": export.shots.map(|s| s.seed),
    })
}

/// A Box of the raw observation: x and y in 0..L-1, every AoI in 1..aoi_max; normalised, each
/// bound multiplied as the observations are.
fn observation_space(world: &WorldConfig, observations: Observations) -> Value {
    let inv = scale_of(world, observations);
    let high: Vec<f32> = world
        .observation_scale()
        .iter()
        .zip(&inv)
        .map(|(h, i)| h * i)
        .collect();
    let low: Vec<f32> = (0..high.len())
        .map(|i| if i < 2 { 0.0 } else { inv[i] })
        .collect();
    json!({
        "type": "Box", "dtype": "float32", "shape": [high.len()], "low": low, "high": high,
    })
}

fn write_json(path: &Path, value: &Value) -> Result<(), InteropError> {
    std::fs::write(path, value.to_string()).map_err(FileError::at(path, "write"))?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ids_follow_minaris_pattern() {
        for id in ["uavmeta/lambda-300-v0", "a/b/c_d-v12", "name-v3"] {
            assert!(check_id(id).is_ok(), "{id}");
        }
        for id in [
            "uavmeta/lambda-300",
            "uavmeta/lambda-1.5-v0",
            "/x-v0",
            "x-v",
            "x y-v0",
        ] {
            let message = check_id(id).unwrap_err().to_string();
            assert!(message.contains(id), "{message}");
        }
        let shots = Some(Shots { n: 100, seed: 1 });
        assert_eq!(default_id("lambda-12.5", None), "uavmeta/lambda-12_5-v0");
        assert_eq!(
            default_id("lambda-300", shots),
            "uavmeta/lambda-300-100shots-v0"
        );
        check_id(&default_id("lambda-12.5-rain-3-3-5-5", shots)).unwrap();
    }
}
