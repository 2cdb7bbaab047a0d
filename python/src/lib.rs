//! The native half of the Python package `uavmeta`: the world of `uavmeta-world` and the dataset
//! format of `uavmeta-proto`, converted to numpy at the edge. It knows nothing of Gymnasium; the
//! Python half (`python/uavmeta`) builds `UavEnv` and `VectorEnv` on [`worlds::Worlds`].
//!
//! - [`task`]: a config file, a task name or one-off arguments to the world and task they mean,
//!   with every bad argument a `ValueError` naming the key and the value.
//! - [`worlds`]: [`worlds::Worlds`], N worlds stepped in one call on numpy arrays with the GIL
//!   released, with Gymnasium's next-step autoreset and the CLI's episode seeds.
//! - [`tasks`]: where each of those worlds takes its task: one for all, a list, or a sampler that
//!   draws a new task at every reset.
//! - [`evaluate`]: a policy scored by the world crate's own evaluation, as the CLI scores it.
//! - [`policies`]: the heuristics (random, stalest, greedy) as batched functions of observations.
//! - [`dataset`]: a `.uavds` file as numpy arrays with its task's metadata.
//!
//! No libtorch and no iceoryx2: a user's own torch never meets ours in one process.
//!
//! ```python
//! import uavmeta._uavmeta as native
//! worlds = native.Worlds(num_envs=4, lam=300.0)
//! obs = worlds.reset([0, 1, 2, 3])          # (4, 12) float32
//! ```

use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;

pub mod dataset;
pub mod evaluate;
pub mod policies;
pub mod task;
pub mod tasks;
pub mod worlds;

/// A `ValueError` with `e`'s message.
pub(crate) fn value_error(e: impl ToString) -> PyErr {
    PyValueError::new_err(e.to_string())
}

#[pymodule]
fn _uavmeta(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<worlds::Worlds>()?;
    m.add_class::<policies::Heuristic>()?;
    m.add_class::<evaluate::Evaluation>()?;
    m.add_function(wrap_pyfunction!(evaluate::evaluate_spec, m)?)?;
    m.add_function(wrap_pyfunction!(evaluate::reference_names, m)?)?;
    m.add_function(wrap_pyfunction!(dataset::load_dataset, m)?)?;
    m.add_function(wrap_pyfunction!(worlds::episode_seed, m)?)?;
    m.add_function(wrap_pyfunction!(policies::checkpoint_spec, m)?)?;
    m.add("DatasetError", m.py().get_type::<dataset::DatasetError>())?;
    m.add("ACTION_MOVES", uavmeta_proto::config::MOVES.to_vec())?;
    Ok(())
}
