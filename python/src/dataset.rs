//! A `.uavds` dataset file (`uavmeta_proto::dataset`) as numpy arrays with its task's metadata.
//!
//! The file is read with the strict `DatasetReader`: any damage (a bad magic, a CRC32 that does
//! not match, a torn tail) raises `uavmeta.DatasetError` with the reader's message, which names
//! the file and the byte offset. The task's lambda and rain come from the config saved beside the
//! file (`FILE.config.toml`, written by `uavmeta collect`) or the one given.

use std::path::{Path, PathBuf};

use numpy::ndarray::Array2;
use numpy::{IntoPyArray, PyArray1};
use pyo3::exceptions::{PyFileNotFoundError, PyOSError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::PyDict;
use uavmeta_proto::config::Config;
use uavmeta_proto::dataset::{DatasetError as ReadError, DatasetReader, Transition};

use crate::task::config_error;
use crate::value_error;

pyo3::create_exception!(
    _uavmeta,
    DatasetError,
    PyValueError,
    "A dataset file that is damaged or not a uavmeta dataset; the message names the file and the byte offset."
);

/// Reads `path` into a dict of numpy arrays (obs, action, reward, next_obs, truncated, task,
/// actor, episode, step, seq; one row per transition) and its metadata (task_name, task_id,
/// devices, world_hash, chunks, and, from the config, lam, rain, rain_moves_every, role,
/// grid_cells, horizon, aoi_max, observation_scale and config_path). `config` defaults to
/// `FILE.config.toml` when that exists. With `normalised`, obs and next_obs are float32 divided
/// by the observation scale (x/(L-1), y/(L-1), A/aoi_max), as the env's `normalised=True`
/// gives them; that needs the config.
#[pyfunction]
#[pyo3(signature = (path, config=None, normalised=false))]
pub fn load_dataset<'py>(
    py: Python<'py>,
    path: PathBuf,
    config: Option<PathBuf>,
    normalised: bool,
) -> PyResult<Bound<'py, PyDict>> {
    let reader = py
        .detach(|| DatasetReader::open(&path))
        .map_err(dataset_error)?;
    let config_path = config.or_else(|| Some(saved_config(&path)).filter(|p| p.exists()));
    let loaded = config_path.as_ref().map(|p| Config::load(p, &[]));
    let loaded = loaded.transpose().map_err(config_error)?;
    let scale = match (&loaded, normalised) {
        (Some(c), true) => Some(c.world.observation_scale()),
        (None, true) => {
            return Err(PyValueError::new_err(format!(
                "normalised = True: the observation scale comes from the dataset's config, and                  {} has none: expected config= or the FILE.config.toml `uavmeta collect` saves",
                path.display()
            )))
        }
        (_, false) => None,
    };
    let out = PyDict::new(py);
    arrays(
        py,
        &out,
        reader.transitions(),
        reader.header().layout().observation_len(),
        scale.as_deref(),
    )?;
    let header = reader.header();
    out.set_item("task_name", &header.task_name)?;
    out.set_item("task_id", header.task)?;
    out.set_item("devices", header.devices)?;
    out.set_item("world_hash", header.world_hash)?;
    out.set_item("chunks", reader.chunks())?;
    out.set_item("path", path.display().to_string())?;
    out.set_item("normalised", normalised)?;
    if let (Some(config_path), Some(config)) = (config_path, loaded) {
        task_metadata(&out, &reader, &config_path, &config)?;
    }
    Ok(out)
}

/// Where `uavmeta collect` saves the config of dataset `path`: `path` with `.config.toml` added.
fn saved_config(path: &Path) -> PathBuf {
    let mut name = path.as_os_str().to_owned();
    name.push(".config.toml");
    PathBuf::from(name)
}

/// The transitions as columns; the observations raw (uint16), or divided by `scale` (float32).
fn arrays(
    py: Python<'_>,
    out: &Bound<'_, PyDict>,
    transitions: &[Transition],
    obs_len: usize,
    scale: Option<&[f32]>,
) -> PyResult<()> {
    let shape = (transitions.len(), obs_len);
    let rows = |f: fn(&Transition) -> &[u16]| {
        let raw = transitions.iter().flat_map(|t| f(t).iter().copied());
        match scale {
            None => matrix(py, shape, raw.collect()),
            Some(scale) => {
                // As `World::write_normalised`: times the f32 reciprocal, so the values equal
                // the env's bit for bit.
                let inv: Vec<f32> = scale.iter().map(|s| 1.0 / s).collect();
                let flat = raw.zip(inv.iter().cycle()).map(|(v, inv)| v as f32 * inv);
                matrix(py, shape, flat.collect())
            }
        }
    };
    out.set_item("obs", rows(|t| &t.obs)?)?;
    out.set_item("next_obs", rows(|t| &t.next_obs)?)?;
    out.set_item("action", column(py, transitions, |t| t.action as i64))?;
    out.set_item("reward", column(py, transitions, |t| t.reward))?;
    out.set_item("truncated", column(py, transitions, |t| t.truncated))?;
    // The horizon is a time limit, never a terminal state: D4RL's and Minari's two columns.
    out.set_item("terminals", column(py, transitions, |_| false))?;
    out.set_item("truncations", column(py, transitions, |t| t.truncated))?;
    out.set_item("task", column(py, transitions, |t| t.task))?;
    out.set_item("actor", column(py, transitions, |t| t.actor))?;
    out.set_item("episode", column(py, transitions, |t| t.episode))?;
    out.set_item("step", column(py, transitions, |t| t.step))?;
    out.set_item("seq", column(py, transitions, |t| t.seq))?;
    Ok(())
}

/// `flat` as an array of `shape`.
fn matrix<T: numpy::Element>(
    py: Python<'_>,
    shape: (usize, usize),
    flat: Vec<T>,
) -> PyResult<Bound<'_, PyAny>> {
    let array = Array2::from_shape_vec(shape, flat).map_err(value_error)?;
    Ok(array.into_pyarray(py).into_any())
}

fn column<'py, T: numpy::Element>(
    py: Python<'py>,
    transitions: &[Transition],
    f: impl Fn(&Transition) -> T,
) -> Bound<'py, PyArray1<T>> {
    transitions
        .iter()
        .map(f)
        .collect::<Vec<T>>()
        .into_pyarray(py)
}

/// lam, rain, rain_moves_every and role of the file's task in `config_path`, after checking the
/// file was collected in that config's world.
fn task_metadata(
    out: &Bound<'_, PyDict>,
    reader: &DatasetReader,
    config_path: &Path,
    config: &Config,
) -> PyResult<()> {
    reader.check_world(config).map_err(dataset_error)?;
    let task = config
        .task(&reader.header().task_name)
        .map_err(config_error)?;
    out.set_item("lam", task.lambda)?;
    out.set_item("rain", task.rain.map(|z| (z.x0, z.y0, z.x1, z.y1)))?;
    out.set_item("rain_moves_every", task.rain_moves_every)?;
    let role = match task.role {
        uavmeta_proto::config::TaskRole::MetaTrain => "meta-train",
        uavmeta_proto::config::TaskRole::MetaTest => "meta-test",
    };
    out.set_item("role", role)?;
    out.set_item("grid_cells", config.world.grid_cells)?;
    out.set_item("horizon", config.world.horizon)?;
    out.set_item("aoi_max", config.world.aoi_max)?;
    out.set_item("observation_scale", config.world.observation_scale())?;
    out.set_item("config_path", config_path.display().to_string())?;
    Ok(())
}

/// A reader error as a Python exception with the reader's message: a missing file is a
/// `FileNotFoundError`, another failed read an `OSError`, anything wrong inside the file a
/// `DatasetError`.
fn dataset_error(e: ReadError) -> PyErr {
    match &e {
        ReadError::File(file) if file.source.kind() == std::io::ErrorKind::NotFound => {
            PyFileNotFoundError::new_err(e.to_string())
        }
        ReadError::File(file) => PyOSError::new_err(format!("{e}: {}", file.source)),
        _ => DatasetError::new_err(e.to_string()),
    }
}
