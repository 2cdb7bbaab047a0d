//! A launch over several seeds (`run.seeds` with more than one entry): one whole supervised run
//! per seed, one after the other, each in `run.dir/seed-S`, and one table whose learned rows are
//! the mean over the seeds with the 95% interval of that mean (Student's t over the seeds'
//! returns, not over episodes), so that no conclusion hangs on one draw.
//!
//! Seed S's run takes `run.seeds = [S]` (its meta-learner's and learners' seed) and
//! `collect.seed + S * 2^32` as its actors' base seed (actor i adds i), so no two seeds share an
//! agent, a dataset or an init.

use std::path::{Path, PathBuf};

use indicatif::MultiProgress;
use uavmeta_proto::config::Config;
use uavmeta_proto::stats::{Estimate, PolicyMetrics};

use super::{launch, LaunchError, LaunchReport, Reuse};
use crate::evaluator::EvaluationRow;

/// Apart by this much, the actor seeds of two run seeds never meet (a task has far fewer actors).
const ACTOR_SEED_STRIDE: u64 = 1 << 32;

/// The config of seed `seed`'s run of a multi-seed launch of `config`.
pub fn seed_config(config: &Config, seed: u64) -> Config {
    let mut c = config.clone();
    c.run.dir = seed_dir(&config.run.dir, seed);
    c.run.seeds = vec![seed];
    c.collect.seed = config
        .collect
        .seed
        .wrapping_add(seed.wrapping_mul(ACTOR_SEED_STRIDE));
    c
}

/// Where seed `seed`'s run of a multi-seed launch into `dir` lives.
pub fn seed_dir(dir: &Path, seed: u64) -> PathBuf {
    dir.join(format!("seed-{seed}"))
}

/// What a launch over several seeds reports: each seed's own report, and their aggregate.
#[derive(Debug, Clone)]
pub struct SeedsReport {
    pub seeds: Vec<(u64, LaunchReport)>,
    /// One row per (task, method) present in every seed's results: means over the seeds, with
    /// the 95% interval over the seeds; references are the first seed's (the same world and
    /// episodes in every seed).
    pub aggregate: LaunchReport,
}

/// Launches `config` once per entry of `run.seeds` (see the module doc). A single seed is a
/// plain [`launch`] into `run.dir` itself.
pub fn launch_seeds(
    exe: PathBuf,
    config: &Config,
    reuse: Reuse,
    terminal: Option<&MultiProgress>,
) -> Result<SeedsReport, LaunchError> {
    if let [seed] = config.run.seeds[..] {
        let report = launch(exe, config, reuse, terminal)?;
        return Ok(SeedsReport {
            seeds: vec![(seed, report.clone())],
            aggregate: report,
        });
    }
    let mut seeds = Vec::new();
    for &seed in &config.run.seeds {
        tracing::info!(seed, of = config.run.seeds.len(), "launching seed");
        let report = launch(exe.clone(), &seed_config(config, seed), reuse, terminal)?;
        seeds.push((seed, report));
    }
    let aggregate = aggregate(&config.run.dir, &seeds);
    Ok(SeedsReport { seeds, aggregate })
}

/// The mean of each (task, method) over the seeds' reports, with the interval over seeds.
fn aggregate(dir: &Path, seeds: &[(u64, LaunchReport)]) -> LaunchReport {
    let (_, first) = &seeds[0];
    let results = first
        .results
        .iter()
        .filter_map(|row| {
            let rows: Vec<&EvaluationRow> = seeds
                .iter()
                .filter_map(|(_, r)| {
                    r.results
                        .iter()
                        .find(|x| x.task == row.task && x.method == row.method)
                })
                .collect();
            (rows.len() == seeds.len()).then(|| mean_row(&rows))
        })
        .collect();
    LaunchReport {
        run: dir.to_path_buf(),
        restarts: seeds.iter().map(|(_, r)| r.restarts).sum(),
        results,
        references: first.references.clone(),
        bounds: first.bounds.clone(),
    }
}

/// One row whose figures are the rows' means, each with the 95% interval over the rows.
fn mean_row(rows: &[&EvaluationRow]) -> EvaluationRow {
    let over = |pick: fn(&PolicyMetrics) -> Estimate| {
        Estimate::from_samples(rows.iter().map(|r| pick(&r.policy).mean))
    };
    EvaluationRow {
        task: rows[0].task.clone(),
        method: rows[0].method.clone(),
        epoch: rows[0].epoch,
        policy: PolicyMetrics {
            episodes: rows.iter().map(|r| r.policy.episodes).sum(),
            ret: over(|p| p.ret),
            aoi: over(|p| p.aoi),
            power_mw: over(|p| p.power_mw),
            outages: over(|p| p.outages),
        },
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn row(method: &str, ret: f64) -> EvaluationRow {
        let estimate = |mean, ci95| Estimate { mean, ci95 };
        let policy = PolicyMetrics {
            episodes: 100,
            ret: estimate(ret, 1.0),
            aoi: estimate(5.0, 0.0),
            power_mw: estimate(0.4, 0.0),
            outages: estimate(0.0, 0.0),
        };
        EvaluationRow::new("lambda-300", method, 100, &policy)
    }

    fn report(rows: Vec<EvaluationRow>) -> LaunchReport {
        LaunchReport {
            run: PathBuf::from("runs/x"),
            restarts: 1,
            results: rows,
            references: vec![row("planner", -6341.0)],
            bounds: Vec::new(),
        }
    }

    #[test]
    fn the_aggregate_is_the_mean_over_seeds_with_the_interval_over_seeds() {
        let seeds = vec![
            (
                0,
                report(vec![row("cql", -7000.0), row("cql-maml", -6900.0)]),
            ),
            (
                1,
                report(vec![row("cql", -7200.0), row("cql-maml", -6800.0)]),
            ),
            (2, report(vec![row("cql", -7100.0)])),
        ];
        let a = aggregate(Path::new("runs/x"), &seeds);
        // cql-maml is missing from seed 2: no row rather than a mean of two.
        assert_eq!(a.results.len(), 1);
        let cql = &a.results[0];
        assert_eq!(cql.method, "cql");
        assert!((cql.policy.ret.mean - -7100.0).abs() < 1e-9);
        // t(0.975, 2) * sd 100 / sqrt(3) = 248.4
        let ci95 = cql.policy.ret.ci95;
        assert!((ci95 - 248.4).abs() < 0.1, "{ci95}");
        assert_eq!((cql.policy.episodes, a.restarts), (300, 3));
        assert_eq!(a.references.len(), 1);
    }

    #[test]
    fn each_seed_runs_in_its_own_directory_with_its_own_actor_seeds() {
        let config = Config::default();
        let (a, b) = (seed_config(&config, 0), seed_config(&config, 1));
        assert_eq!(a.run.dir, config.run.dir.join("seed-0"));
        assert_eq!(b.run.seeds, vec![1]);
        assert_ne!(a.collect.seed, b.collect.seed);
        assert!(b.collect.seed.abs_diff(a.collect.seed) >= ACTOR_SEED_STRIDE);
    }
}
