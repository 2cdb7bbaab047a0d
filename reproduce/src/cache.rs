//! The plan's results in the shared cache, beside the datasets and inits `runs` keeps there: the
//! heuristics' rows (`OUT/cache/heuristics/`), each seed's online DQN reference rows
//! (`seed-S/references/`) and fine-tuning runs (`seed-S/runs/`), and every job's completion
//! marker (`OUT/cache/jobs/ID.done`).
//!
//! Every file is written to a temporary file in its own directory and renamed into place
//! ([`write`]), so a job killed mid-write leaves the old file or none,
//! never a torn one. A marker is written last, after everything its job makes, and holds the
//! job's stamp (the config's fingerprint and the job's parameters): a job is done exactly when its
//! marker holds the stamp the plan expects. Results are TOML: floats are written in Rust's
//! shortest round-trip form and read back to the same bits, so the CSVs drawn from a cached result
//! are the bytes of those drawn from the one in memory.

use std::path::{Path, PathBuf};

use serde::de::DeserializeOwned;
use serde::{Deserialize, Serialize};
use uavmeta_meta::{create_dir, MetaError};
use uavmeta_proto::fs::{write_atomic, FileError};
use uavmeta_proto::stats::PolicyMetrics;
use uavmeta_world::heuristics::REFERENCES;

use crate::runs::{seed_dir, ModelPlanned, ModelPlannerKey, RefKey, RunKey, RunResult};
use crate::{HeuristicRef, ReproduceError};

/// Where the job `id`'s completion marker lives.
pub fn marker_path(out: &Path, id: &str) -> PathBuf {
    out.join("cache").join("jobs").join(format!("{id}.done"))
}

/// Whether job `id` finished with `stamp`.
pub fn is_done(out: &Path, id: &str, stamp: &str) -> bool {
    std::fs::read_to_string(marker_path(out, id)).is_ok_and(|text| text == stamp)
}

/// Marks job `id` finished with `stamp`.
pub fn mark_done(out: &Path, id: &str, stamp: &str) -> Result<(), ReproduceError> {
    write(&marker_path(out, id), stamp)
}

/// Writes `text` to `path` atomically (`uavmeta_proto::fs::write_atomic`), creating its
/// directory.
pub fn write(path: &Path, text: &str) -> Result<(), ReproduceError> {
    create_dir(path.parent().unwrap_or(Path::new(".")))?;
    write_atomic(path, text.as_bytes()).map_err(MetaError::from)?;
    Ok(())
}

fn save<T: Serialize>(path: &Path, value: &T) -> Result<(), ReproduceError> {
    let text = toml::to_string(value).expect("the cache's results always serialise");
    write(path, &text)
}

fn load<T: DeserializeOwned>(path: &Path) -> Result<T, ReproduceError> {
    let text = std::fs::read_to_string(path)
        .map_err(FileError::at(path, "read"))
        .map_err(MetaError::from)?;
    toml::from_str(&text).map_err(|e| ReproduceError::Cache {
        path: path.to_path_buf(),
        message: e.to_string().trim_end().replace('\n', " "),
    })
}

/// The heuristics' rows of `key` (seed-free).
pub fn heuristics_path(out: &Path, key: &RefKey) -> PathBuf {
    let name = format!("{}.episodes-{}.toml", key.task, key.episodes);
    out.join("cache").join("heuristics").join(name)
}

/// Seed `seed`'s online DQN reference row of `key`.
pub fn reference_path(out: &Path, seed: u64, key: &RefKey) -> PathBuf {
    let name = format!("{}.episodes-{}.toml", key.task, key.episodes);
    seed_dir(out, seed).join("references").join(name)
}

/// Seed `seed`'s planner in the world its shots of `key` fit.
pub fn model_planner_path(out: &Path, seed: u64, key: &ModelPlannerKey) -> PathBuf {
    let name = format!(
        "{}.shots-{}.episodes-{}.toml",
        key.task, key.shots, key.episodes
    );
    seed_dir(out, seed).join("model-planners").join(name)
}

/// Seed `seed`'s fine-tuning run of `key`.
pub fn run_path(out: &Path, seed: u64, key: &RunKey) -> PathBuf {
    let name = format!(
        "{}.shots-{}.tasks-{}.episodes-{}.toml",
        key.method.name(),
        key.shots,
        key.meta_tasks,
        key.eval_episodes
    );
    seed_dir(out, seed).join("runs").join(&key.task).join(name)
}

#[derive(Serialize, Deserialize)]
struct Policies {
    policies: Vec<NamedMetrics>,
}

#[derive(Serialize, Deserialize)]
struct NamedMetrics {
    name: String,
    metrics: PolicyMetrics,
}

pub fn save_heuristics(path: &Path, h: &HeuristicRef) -> Result<(), ReproduceError> {
    let policies = (h.policies.iter())
        .map(|&(name, metrics)| NamedMetrics {
            name: name.to_string(),
            metrics,
        })
        .collect();
    save(path, &Policies { policies })
}

pub fn load_heuristics(path: &Path, key: &RefKey) -> Result<HeuristicRef, ReproduceError> {
    let file: Policies = load(path)?;
    let policies = file.policies.into_iter().map(|p| {
        let known = REFERENCES.iter().map(|s| s.name()).find(|&n| n == p.name);
        known
            .map(|name| (name, p.metrics))
            .ok_or(ReproduceError::Cache {
                path: path.to_path_buf(),
                message: format!("`{}` is not one of the reference policies", p.name),
            })
    });
    Ok(HeuristicRef {
        task: key.task.clone(),
        episodes: key.episodes,
        policies: policies.collect::<Result<_, _>>()?,
    })
}

#[derive(Serialize, Deserialize)]
struct Reference {
    metrics: PolicyMetrics,
}

pub fn save_reference(path: &Path, metrics: PolicyMetrics) -> Result<(), ReproduceError> {
    save(path, &Reference { metrics })
}

pub fn load_reference(path: &Path) -> Result<PolicyMetrics, ReproduceError> {
    Ok(load::<Reference>(path)?.metrics)
}

/// [`ModelPlanned`] as written: the metrics, or why the shots fit no world.
#[derive(Serialize, Deserialize)]
struct ModelPlanner {
    metrics: Option<PolicyMetrics>,
    no_fitted_world: Option<String>,
}

pub fn save_model_planner(path: &Path, planned: &ModelPlanned) -> Result<(), ReproduceError> {
    let file = ModelPlanner {
        metrics: planned.as_ref().ok().copied(),
        no_fitted_world: planned.as_ref().err().cloned(),
    };
    save(path, &file)
}

pub fn load_model_planner(path: &Path) -> Result<ModelPlanned, ReproduceError> {
    match load::<ModelPlanner>(path)? {
        ModelPlanner {
            metrics: Some(m), ..
        } => Ok(Ok(m)),
        ModelPlanner {
            no_fitted_world: Some(why),
            ..
        } => Ok(Err(why)),
        _ => Err(ReproduceError::Cache {
            path: path.to_path_buf(),
            message: "holds neither metrics nor why the shots fit no world".into(),
        }),
    }
}

pub fn save_run(path: &Path, result: &RunResult) -> Result<(), ReproduceError> {
    save(path, result)
}

pub fn load_run(path: &Path) -> Result<RunResult, ReproduceError> {
    load(path)
}

#[cfg(test)]
mod tests {
    use super::*;
    use uavmeta_learner::train::EpochRow;
    use uavmeta_proto::stats::EpisodeMetrics;
    use uavmeta_proto::stats::Estimate;
    use uavmeta_world::rollout::Trajectory;

    fn metrics(x: f64) -> PolicyMetrics {
        let e = |mean, ci95| Estimate { mean, ci95 };
        PolicyMetrics {
            episodes: 3,
            ret: e(x, f64::NAN),
            aoi: e(0.1 + 0.2, 1e-300),
            power_mw: e(-0.0, f64::MAX),
            outages: e(f64::INFINITY, 5e-324),
        }
    }

    /// What the figures print of a result: every float through `{}`, as their CSVs do.
    fn printed(r: &RunResult) -> String {
        format!("{r:?}")
    }

    #[test]
    fn a_cached_run_reads_back_to_the_same_bits() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("a/b/run.toml");
        let row = EpochRow {
            epoch: 1,
            steps: 10,
            td_loss: 1.0 / 3.0,
            conservative_loss: -7.25e-17,
            mean_q: -6327.123456789012,
            policy: metrics(-12898.000000000002),
            seconds: 0.1,
            network_epoch: 1,
        };
        let result = RunResult {
            rows: vec![row, EpochRow { epoch: 2, ..row }],
            trajectory: Some(Trajectory {
                cells: vec![(0, 1), (2, 3)],
                metrics: EpisodeMetrics {
                    ret: -1.5,
                    aoi: 2.0,
                    power_mw: 0.47,
                    outages: 2,
                },
            }),
        };
        save_run(&path, &result).unwrap();
        let back = load_run(&path).unwrap();
        assert_eq!(printed(&back), printed(&result));
        let bits = |r: &RunResult| {
            r.rows
                .iter()
                .map(|r| r.mean_q.to_bits())
                .collect::<Vec<_>>()
        };
        assert_eq!(bits(&back), bits(&result));
        // No temporary file is left beside it.
        assert_eq!(
            std::fs::read_dir(path.parent().unwrap()).unwrap().count(),
            1
        );
    }

    #[test]
    fn a_torn_or_foreign_file_is_refused_by_name() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("run.toml");
        std::fs::write(&path, "rows = [{ epoch = 1, ste").unwrap();
        let error = load_run(&path).unwrap_err().to_string();
        assert!(error.contains("run.toml"), "{error}");
        let key = RefKey {
            task: "t".into(),
            episodes: 2,
        };
        let policy = NamedMetrics {
            name: "bogus".into(),
            metrics: metrics(1.0),
        };
        save(
            &path,
            &Policies {
                policies: vec![policy],
            },
        )
        .unwrap();
        let error = load_heuristics(&path, &key).unwrap_err().to_string();
        assert!(error.contains("`bogus`"), "{error}");
    }

    #[test]
    fn a_marker_counts_only_with_its_stamp() {
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path();
        assert!(!is_done(out, "run/seed-0/x", "config 1"));
        mark_done(out, "run/seed-0/x", "config 1").unwrap();
        assert!(is_done(out, "run/seed-0/x", "config 1"));
        assert!(!is_done(out, "run/seed-0/x", "config 2"));
    }
}
