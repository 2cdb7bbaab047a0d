//! Flat NumPy arrays in the D4RL convention, which d3rlpy's
//! `MDPDataset(observations, actions, rewards, terminals, timeouts)` takes as they are.
//!
//! Rows go run by run ([`crate::runs`]): one row per transition, then one row holding the run's
//! final next observation, with `timeouts` = 1, action 0 and reward 0. A timeout row is never a
//! transition: d3rlpy gives an episode that ends in a timeout one transition fewer than its rows
//! (its last observation is only the one before's next observation), and D4RL's
//! `qlearning_dataset` skips timeout rows. So both see exactly the exported transitions with
//! their true next observations, however short the runs. `next_observations` spells those out
//! per row for loaders that read (s, a, r, s') directly; a timeout row repeats its own
//! observation there. `terminals` are all 0: the world has no terminal state (docs/MODEL.md section
//! 1).
//!
//! | array               | dtype   | shape       | holds                                         |
//! | ------------------- | ------- | ----------- | --------------------------------------------- |
//! | `observations`      | float32 | (rows, 2+K) | raw [x, y, A_1..A_K], as in the dataset file  |
//! | `actions`           | int64   | (rows,)     | `move * K + device`                           |
//! | `rewards`           | float32 | (rows,)     | unscaled r(t)                                 |
//! | `terminals`         | float32 | (rows,)     | 0                                             |
//! | `timeouts`          | float32 | (rows,)     | 1 on each run's last row                      |
//! | `next_observations` | float32 | (rows, 2+K) | raw s(t+1)                                    |
//!
//! Observations stay raw, as learners read them from the file; divide by
//! `WorldConfig::observation_scale` (or use a d3rlpy observation scaler) to normalise.

use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::Path;

use npyz::npz::NpzWriter;
use npyz::{AutoSerialize, WriterBuilder};
use uavmeta_proto::dataset::Transition;
use uavmeta_proto::fs::FileError;

use crate::{prepare_output, Export, InteropError};

/// What [`write`] wrote.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct NpzSummary {
    pub transitions: usize,
    pub runs: usize,
    /// Transitions plus one timeout row per run.
    pub rows: usize,
}

/// The six arrays, row-major.
#[derive(Default)]
struct Columns {
    observations: Vec<f32>,
    actions: Vec<i64>,
    rewards: Vec<f32>,
    terminals: Vec<f32>,
    timeouts: Vec<f32>,
    next_observations: Vec<f32>,
}

impl Columns {
    fn from_runs(runs: &[Vec<Transition>]) -> Self {
        let mut columns = Self::default();
        for run in runs {
            for t in run {
                columns.push(&t.obs, t.action.into(), t.reward, false, &t.next_obs);
            }
            let last = &run.last().expect("a run is never empty").next_obs;
            columns.push(last, 0, 0.0, true, last);
        }
        columns
    }

    fn push(&mut self, obs: &[u16], action: i64, reward: f32, timeout: bool, next_obs: &[u16]) {
        self.observations.extend(obs.iter().map(|&v| f32::from(v)));
        self.actions.push(action);
        self.rewards.push(reward);
        self.terminals.push(0.0);
        self.timeouts.push(if timeout { 1.0 } else { 0.0 });
        self.next_observations
            .extend(next_obs.iter().map(|&v| f32::from(v)));
    }
}

/// Writes `export` to the new file `out`, atomically: a failed export leaves no file behind.
pub fn write(export: &Export, out: &Path) -> Result<NpzSummary, InteropError> {
    let dir = prepare_output(out)?;
    let columns = Columns::from_runs(&export.runs);
    let rows = columns.actions.len();
    let width = export.config.world.layout().observation_len() as u64;
    let matrix = [rows as u64, width];
    let vector = [rows as u64];

    let mut file = tempfile::NamedTempFile::new_in(dir)
        .map_err(FileError::at(dir, "create a file in the directory"))?;
    let write_all = |file: &mut File| -> std::io::Result<()> {
        let mut npz = NpzWriter::new(BufWriter::new(file));
        array(&mut npz, "observations", &matrix, &columns.observations)?;
        array(&mut npz, "actions", &vector, &columns.actions)?;
        array(&mut npz, "rewards", &vector, &columns.rewards)?;
        array(&mut npz, "terminals", &vector, &columns.terminals)?;
        array(&mut npz, "timeouts", &vector, &columns.timeouts)?;
        array(
            &mut npz,
            "next_observations",
            &matrix,
            &columns.next_observations,
        )?;
        npz.zip_writer().finish()?.flush()
    };
    write_all(file.as_file_mut()).map_err(FileError::at(out, "write the .npz"))?;
    file.persist_noclobber(out)
        .map_err(|e| FileError::at(out, "create")(e.error))?;
    Ok(NpzSummary {
        transitions: export.transitions(),
        runs: export.runs.len(),
        rows,
    })
}

/// One array `name` of `shape`, row-major `values`.
fn array<T: AutoSerialize + Copy, W: Write + std::io::Seek>(
    npz: &mut NpzWriter<W>,
    name: &str,
    shape: &[u64],
    values: &[T],
) -> std::io::Result<()> {
    let mut writer = npz
        .array::<T>(name, Default::default())?
        .default_dtype()
        .shape(shape)
        .begin_nd()?;
    writer.extend(values.iter().copied())?;
    writer.finish()
}
