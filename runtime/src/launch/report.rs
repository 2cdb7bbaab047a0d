//! The results table a launch ends with: the references (random, the heuristics, the planner,
//! the online DQN agents) and every learner's last evaluation, per meta-test task.

use std::collections::BTreeMap;
use std::path::PathBuf;

use uavmeta_learner::transitions::load_shots;
use uavmeta_proto::config::{Config, TaskRole};
use uavmeta_proto::method::{Method, MODEL_BASED, MODEL_PLANNER, NO_FITTED_WORLD};
use uavmeta_proto::stats;
use uavmeta_world::heuristics::{model_planner_metrics, reference_metrics, PolicySpec, REFERENCES};
use uavmeta_world::world::World;

use super::LaunchError;
use crate::evaluator::{self, EvaluationRow};
use crate::run_dir::RunDir;
use uavmeta_proto::fs::FileError;

/// What a finished launch reports.
#[derive(Debug, Clone)]
pub struct LaunchReport {
    pub run: PathBuf,
    pub restarts: u32,
    /// The last evaluation of every (task, method).
    pub results: Vec<EvaluationRow>,
    /// The heuristics on every meta-test task, over the evaluator's episodes: what a learned
    /// return is measured against.
    pub references: Vec<EvaluationRow>,
    /// Each meta-test task's return bound (`World::return_bound`): no policy scores above it.
    pub bounds: Vec<(String, f64)>,
}

/// Where a row goes in its task's block: the references (random, the heuristics, the planner,
/// then the online DQN agent)
/// first, then the learners, the model planner last; `None` for a method the table does not
/// know.
pub(super) fn row_rank(method: &str) -> Option<usize> {
    let references = REFERENCES.iter().map(ToString::to_string);
    let references = references.chain([Method::OnlineDqn.name()]);
    let learners = Method::learners().map(Method::name);
    let mut order = references
        .chain(learners)
        .chain([MODEL_PLANNER.to_string()]);
    order.position(|name| name == method)
}

/// Whether a row is a reference (random, a heuristic, the planner or the online DQN agent)
/// rather than a learner.
pub(super) fn is_reference(method: &str) -> bool {
    row_rank(method).is_some_and(|rank| rank <= REFERENCES.len())
}

/// Whether a row is a model-based method's, shown in a section of its own.
fn is_model_based(method: &str) -> bool {
    method == MODEL_PLANNER || Method::from_name(method).is_some_and(Method::model_based)
}

/// The planner in the world the run's shots identify, on each meta-test task: the shots the
/// fine-tuning runs of `seed` read (`learner.shots` of the task's dataset), the fit told only the
/// world's form (`uavmeta_world::identify`), the plan made in the fitted world from each state
/// the true world shows and played there. No row where the shots identify no world (rain) or
/// the dataset is missing.
pub(super) fn model_planner_rows(config: &Config, run: &RunDir, seed: u64) -> Vec<EvaluationRow> {
    let episodes = config.learner.eval_episodes;
    config
        .tasks_with_role(TaskRole::MetaTest)
        .filter_map(|task| {
            let dataset = run.dataset(task);
            let shots = load_shots(config, task, &dataset, config.fine_tune_shots(), seed);
            let metrics =
                match shots.map(|s| model_planner_metrics(config, task, &s.rows, episodes)) {
                    Ok(Ok(metrics)) => metrics,
                    Ok(Err(why)) => {
                        tracing::info!(task = %task.name, %why, "no model-planner row");
                        return None;
                    }
                    Err(error) => {
                        tracing::warn!(task = %task.name, %error, "no model-planner row");
                        return None;
                    }
                };
            Some(EvaluationRow::new(&task.name, MODEL_PLANNER, 0, &metrics))
        })
        .collect()
}

/// What the row's network number counts (`Method::network_label`), `-` for a reference.
fn network(row: &EvaluationRow) -> String {
    match Method::from_name(&row.method) {
        Some(method) if !is_reference(&row.method) => method.network_label(row.epoch),
        _ => "-".into(),
    }
}

/// Each reference policy on each meta-test task, over the episodes the evaluator scores
/// checkpoints on.
pub(super) fn reference_rows(config: &Config) -> Vec<EvaluationRow> {
    config
        .tasks_with_role(TaskRole::MetaTest)
        .flat_map(|task| {
            reference_metrics(config, task, config.learner.eval_episodes)
                .into_iter()
                .map(|(spec, m)| EvaluationRow::new(&task.name, &spec.to_string(), 0, &m))
        })
        .collect()
}

/// Each meta-test task's return bound.
pub(super) fn bounds(config: &Config) -> Vec<(String, f64)> {
    config
        .tasks_with_role(TaskRole::MetaTest)
        .map(|task| {
            let bound = World::new(&config.world, task, 0).return_bound();
            (task.name.clone(), bound)
        })
        .collect()
}

/// The last row of every (task, method) in the evaluator's CSV.
pub(super) fn latest_results(run: &RunDir) -> Result<Vec<EvaluationRow>, LaunchError> {
    let path = run.evaluations_csv();
    if !path.exists() {
        return Ok(Vec::new());
    }
    let rows = evaluator::read_rows(&path).map_err(FileError::at(&path, "read"))?;
    let mut latest: BTreeMap<(String, String), EvaluationRow> = BTreeMap::new();
    for row in rows {
        latest.insert((row.task.clone(), row.method.clone()), row);
    }
    Ok(latest.into_values().collect())
}

/// The results table `uavmeta launch` ends with: per task, the references (heuristics, online
/// DQN), a rule, the learners that read the shots alone at their last evaluated network, then
/// the model-based section under a line saying what it is told. Power in mW, as everywhere.
pub fn results_table(report: &LaunchReport) -> String {
    let mut out = format!(
        "run {} ({} restarts)\n",
        report.run.display(),
        report.restarts
    );
    if report.results.is_empty() {
        out.push_str("no evaluations\n");
        return out;
    }
    let header = format!(
        "{:<14} {:<15} {:>9} {:>22} {:>12} {:>14} {:>18} {:>12}",
        "task", "method", "epoch", "return", "vs planner", "AoI", "power (mW)", "outages"
    );
    out.push_str(&header);
    out.push('\n');
    let mut tasks: Vec<&str> = report.results.iter().map(|r| r.task.as_str()).collect();
    tasks.dedup();
    for task in tasks {
        let rows = report.references.iter().chain(&report.results);
        let mut rows: Vec<&EvaluationRow> = rows.filter(|r| r.task == task).collect();
        rows.sort_by_key(|r| row_rank(&r.method));
        let planner = PolicySpec::Planner.to_string();
        let planner = rows
            .iter()
            .find(|r| r.method == planner)
            .map(|r| r.policy.ret.mean);
        // Rows above the planner: there it is not the best achievable, and the column then
        // says how far below the best row found, not below the optimum.
        let above = |r: &EvaluationRow| planner.is_some_and(|p| r.policy.ret.mean > p);
        let greedy = PolicySpec::Greedy.to_string();
        let greedy = rows
            .iter()
            .find(|r| r.method == greedy)
            .map(|r| r.policy.ret.mean);
        // Learned rows below the greedy heuristic: they have not learnt the task from the shots.
        let below = |r: &EvaluationRow| {
            !is_reference(&r.method) && greedy.is_some_and(|g| r.policy.ret.mean < g)
        };
        for (i, r) in rows.iter().enumerate() {
            let reference = is_reference(&r.method);
            if i > 0 && !reference && is_reference(&rows[i - 1].method) {
                out.push_str(&format!("{}\n", "-".repeat(header.len())));
            }
            if is_model_based(&r.method) && (i == 0 || !is_model_based(&rows[i - 1].method)) {
                out.push_str(&format!("-- {MODEL_BASED}\n"));
            }
            out.push_str(&format!(
                "{:<14} {:<15} {:>9} {:>22} {:>12} {:>14} {:>18} {:>12}\n",
                r.task,
                r.method,
                network(r),
                format!("{:.1}", r.policy.ret),
                // Returns are costs: a row 3% below the planner reads -3.0%.
                planner.map_or("-".to_string(), |p| {
                    let mark = if below(r) { stats::BELOW_GREEDY } else { "" };
                    format!("{}{mark}", stats::gap_to_planner(r.policy.ret.mean, p))
                }),
                format!("{:.2}", r.policy.aoi),
                format!("{:.3}", r.policy.power_mw),
                format!("{:.1}", r.policy.outages),
            ));
        }
        if let (Some(p), Some((_, bound))) =
            (planner, report.bounds.iter().find(|(t, _)| t == task))
        {
            out.push_str(&format!(
                "{task}: no policy can score above {bound:.1}, {:+.1}% vs planner (docs/MODEL.md section 9)\n",
                stats::percent_from(*bound, p)
            ));
        }
        // A model-based row with no model-planner beside it: the shots identified no world.
        let learned_with_model = rows
            .iter()
            .any(|r| is_model_based(&r.method) && r.method != MODEL_PLANNER);
        if learned_with_model && !rows.iter().any(|r| r.method == MODEL_PLANNER) {
            out.push_str(&format!("{task}: {NO_FITTED_WORLD}\n"));
        }
        let below_greedy: Vec<&str> = rows
            .iter()
            .filter(|r| below(r))
            .map(|r| r.method.as_str())
            .collect();
        if let (Some(g), false) = (greedy, below_greedy.is_empty()) {
            out.push_str(&format!(
                "{task}: {} below the greedy heuristic's {g:.1}, not a policy learnt from these shots: {} (docs/EXPERIMENTS.md B9)\n",
                stats::BELOW_GREEDY,
                below_greedy.join(", ")
            ));
        }
        if let (Some(p), Some(best)) = (
            planner,
            rows.iter()
                .filter(|r| above(r))
                .map(|r| r.policy.ret.mean)
                .reduce(f64::max),
        ) {
            out.push_str(&format!(
                "{} above the planner: on {task} the planner is a search, not the optimum, and the best row beats it by {:.1}% (docs/MODEL.md section 9)\n",
                stats::ABOVE_PLANNER,
                stats::percent_from(best, p)
            ));
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use uavmeta_proto::stats::{EpisodeMetrics, PolicyMetrics};

    use super::*;

    fn row(method: &str, ret: f64, power_mw: f64) -> EvaluationRow {
        let episode = EpisodeMetrics {
            ret,
            aoi: 5.0,
            power_mw,
            outages: 0,
        };
        EvaluationRow::new(
            "lambda-300",
            method,
            40,
            &PolicyMetrics::from_episodes(&[episode]),
        )
    }

    #[test]
    fn the_results_table_puts_references_above_a_rule_and_power_in_milliwatts() {
        let report = LaunchReport {
            run: PathBuf::from("runs/x"),
            restarts: 0,
            results: vec![
                row("maml-init", -7400.0, 0.5),
                row("cql-maml", -7100.0, 0.5),
                row("online-dqn", -7000.0, 0.5),
                row("cql", -16000.0, 0.5),
                row("dyna-cql", -6900.0, 0.5),
            ],
            references: vec![
                row("greedy", -7800.0, 0.325),
                row("random", -13000.0, 1.3),
                row("planner", -6500.0, 0.3),
            ],
            bounds: vec![("lambda-300".into(), -5473.0)],
        };
        let table = results_table(&report);
        // The rows, without the header and the bound's line under them.
        let methods: Vec<&str> = table
            .lines()
            .skip(2)
            .filter(|l| !l.starts_with("lambda-300:"))
            .map(|l| match l.starts_with("-- ") {
                true => "--",
                false => l.split_whitespace().nth(1).unwrap_or(l),
            })
            .collect();
        let rule = "-".repeat(10);
        let expected = [
            "random",
            "greedy",
            "planner",
            "online-dqn",
            &rule,
            "cql",
            "cql-maml",
            "maml-init",
            "--",
            "dyna-cql",
        ];
        assert_eq!(methods.len(), expected.len(), "{table}");
        for (got, want) in methods.iter().zip(expected) {
            assert!(
                got.starts_with(want),
                "{got} where {want} belongs:\n{table}"
            );
        }
        assert!(table.contains("power (mW)"), "{table}");
        // Nothing beats the planner here, so nothing is marked; the bound is said.
        assert!(!table.contains(stats::ABOVE_PLANNER), "{table}");
        assert!(
            table.contains("lambda-300: no policy can score above -5473.0, +15.8% vs planner"),
            "{table}"
        );
        assert!(table.contains("0.325 ± 0.000"), "{table}");
        // Each row's distance to the planner: cql-maml's -7100 is 9.2% below its -6500.
        let cql_maml = table.lines().find(|l| l.contains(" cql-maml ")).unwrap();
        assert!(cql_maml.contains("-9.2%"), "{table}");
        // cql's -16000 is below greedy's -7800: marked, and the note names it alone.
        let below = stats::BELOW_GREEDY;
        let cql = table.lines().find(|l| l.contains(" cql ")).unwrap();
        assert!(cql.contains(&format!("-146.2%{below}")), "{table}");
        assert!(!cql_maml.contains(below), "{table}");
        let note = format!("lambda-300: {below} below the greedy heuristic's -7800.0, not a policy learnt from these shots: cql (");
        assert!(table.contains(&note), "{table}");
        // dyna-cql without a model-planner row: the shots fitted no world, and the table says so.
        assert!(
            table.contains("lambda-300: the shots fit no world (they show rain"),
            "{table}"
        );
        // References have no network number; a fine-tuned row gives its epoch, w0 its
        // meta-epoch; the model-based section says what it is told.
        assert!(
            table
                .lines()
                .any(|l| l.starts_with("lambda-300     greedy                  -")),
            "{table}"
        );
        let line = |m: &str| {
            table
                .lines()
                .find(|l| l.contains(&format!(" {m} ")))
                .unwrap()
        };
        assert!(line("cql-maml").contains(" 40 "), "{table}");
        assert!(line("maml-init").contains(" meta-40 "), "{table}");
        assert!(table.contains(&format!("-- {MODEL_BASED}")), "{table}");
    }

    #[test]
    fn the_fitted_worlds_note_appears_only_without_a_model_planner_row() {
        let report = |results| LaunchReport {
            run: PathBuf::from("runs/x"),
            restarts: 0,
            results,
            references: vec![row("planner", -6500.0, 0.3)],
            bounds: vec![],
        };
        let note = "lambda-300: the shots fit no world";
        let fitted = report(vec![
            row("dyna-cql", -6600.0, 0.4),
            row(MODEL_PLANNER, -6500.0, 0.3),
        ]);
        assert!(
            !results_table(&fitted).contains(note),
            "{}",
            results_table(&fitted)
        );
        let unfitted = report(vec![
            row("dyna-cql", -6600.0, 0.4),
            row("cql", -6600.0, 0.4),
        ]);
        assert!(
            results_table(&unfitted).contains(note),
            "{}",
            results_table(&unfitted)
        );
        let model_free = report(vec![row("cql", -6600.0, 0.4)]);
        assert!(
            !results_table(&model_free).contains(note),
            "{}",
            results_table(&model_free)
        );
    }

    #[test]
    fn a_row_above_the_planner_is_marked_and_the_margin_said() {
        let report = LaunchReport {
            run: PathBuf::from("runs/x"),
            restarts: 0,
            results: vec![row("online-dqn", -6100.0, 0.5), row("cql", -6400.0, 0.5)],
            references: vec![row("planner", -6500.0, 0.3)],
            bounds: Vec::new(),
        };
        let table = results_table(&report);
        let line = |method: &str| {
            let pattern = format!(" {method} ");
            table
                .lines()
                .find(|l| l.contains(&pattern))
                .unwrap()
                .to_string()
        };
        assert!(line("online-dqn").contains("+6.2%*"), "{table}");
        assert!(line("cql").contains("+1.5%*"), "{table}");
        assert!(!line("planner").contains('*'), "{table}");
        // The footnote gives the best row's margin.
        let note = table.lines().last().unwrap();
        assert!(
            note.starts_with("* above the planner: on lambda-300"),
            "{table}"
        );
        assert!(note.contains("by 6.2%"), "{table}");
    }
}
