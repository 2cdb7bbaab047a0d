//! Per experiment: its CSV files (one row per method, seed and epoch, raw returns), its PNG charts
//! (returns / 100, the paper's scale, mean over seeds with a 95% band) and the markdown body of
//! its `summary.md`, ending with the claims of docs/MODEL.md section 6 it tests. One file per
//! figure; this module holds what they share: the context they read, the reference lines and the
//! chart and CSV helpers.

use std::fmt::Write as _;
use std::path::Path;

use uavmeta_learner::train::EpochRow;
use uavmeta_meta::write_file;
use uavmeta_plot::{self as plot, Band, Bar, LineChart, Reference, Series, TrajectoryChart};
use uavmeta_proto::config::{Config, RainZone, TaskConfig};
use uavmeta_proto::method::{Algo, Method, Start, MODEL_BASED, MODEL_PLANNER, NO_FITTED_WORLD};
use uavmeta_proto::stats::{self, Estimate, PolicyMetrics};
use uavmeta_world::heuristics::PolicySpec;
use uavmeta_world::world::World;

use crate::claims::{
    self, converged_at, final_return, mean_swing, return_at, settle_epoch, Claim, Verdict,
};
use crate::runs::{Init, InitKey, MetaCurve, ModelPlannerKey, RunKey, SeedResult, W0};
use crate::{agent_tasks, rain_tasks, Experiment, HeuristicRef, ReproduceConfig, ReproduceError};

mod aoi_power;
mod convergence;
mod meta_training;
mod online_dqn;
mod resilience;
pub use resilience::PATHS;
mod shots;
mod tasks;

/// The paper reads convergence off at epoch 40 (CQL-MAML) and 100 (CQL); figure 9 at 100 and 200.
const EPOCH_40: usize = 40;
const EPOCH_100: usize = 100;

/// The CQL fine-tunings from the four inits.
const CQL_INITS: [Method; 4] = [
    Method::CQL_MAML,
    Method::CQL_PRETRAIN,
    Method::CQL_CONTEXT,
    Method::CQL,
];

/// [`CQL_INITS`], then each of `learner.baselines` from w0 and from a random init: what figures
/// 6 to 9 compare (figure 7 each method with an init at every task count).
pub fn compared(config: &Config) -> Vec<Method> {
    let mut methods = CQL_INITS.to_vec();
    add_baselines(config, &mut methods);
    methods
}

/// Figure 5's methods: [`CQL_INITS`], the DQN ablation (DQN, DQN-MAML), then the baselines.
pub fn fine_tuned(config: &Config) -> Vec<Method> {
    let mut methods = CQL_INITS.to_vec();
    methods.extend([Method::DQN, Method::DQN_MAML]);
    add_baselines(config, &mut methods);
    methods
}

/// Each of `learner.baselines` from w0 and from a random init, after `methods`.
fn add_baselines(config: &Config, methods: &mut Vec<Method>) {
    for &algo in &config.learner.baselines {
        for method in [
            Method::tuned(algo, Start::W0),
            Method::tuned(algo, Start::Random),
        ] {
            if !methods.contains(&method) && algo != Algo::CQL {
                methods.push(method);
            }
        }
    }
}

/// What every experiment reads.
pub struct Context<'a> {
    pub config: &'a Config,
    pub reproduce: &'a ReproduceConfig,
    /// In seed order.
    pub seeds: &'a [SeedResult],
    pub heuristics: &'a [HeuristicRef],
}

/// An experiment's `summary.md` body and its claims.
pub struct Section {
    pub body: String,
    pub claims: Vec<Claim>,
}

/// The run of `method` on the unseen task with `shots` shots (from the w0 of the first
/// `meta_tasks` meta-train tasks when meta-trained).
pub fn unseen_key(
    config: &Config,
    r: &ReproduceConfig,
    method: Method,
    shots: usize,
    meta_tasks: usize,
) -> RunKey {
    RunKey {
        task: r.unseen_task.clone(),
        method,
        shots,
        meta_tasks: Init::of(method).map_or(0, |_| meta_tasks),
        eval_episodes: config.learner.eval_episodes,
    }
}

/// The run of `method` on a rain task (figure 9).
pub fn rain_key(config: &Config, r: &ReproduceConfig, task: &TaskConfig, method: Method) -> RunKey {
    RunKey {
        task: task.name.clone(),
        eval_episodes: r.resilience_eval_episodes,
        ..unseen_key(config, r, method, r.main_shots, r.meta_tasks)
    }
}

/// Writes `experiment`'s files into `dir`.
pub fn write(ctx: &Context, experiment: Experiment, dir: &Path) -> Result<Section, ReproduceError> {
    match experiment {
        Experiment::MetaTraining => meta_training::meta_training(ctx, dir),
        Experiment::Convergence => convergence::convergence(ctx, dir),
        Experiment::Shots => shots::shots(ctx, dir),
        Experiment::Tasks => tasks::tasks(ctx, dir),
        Experiment::AoiPower => aoi_power::aoi_power(ctx, dir),
        Experiment::Resilience => resilience::resilience(ctx, dir),
        Experiment::OnlineDqn => online_dqn::online_dqn(ctx, dir),
    }
}

impl Context<'_> {
    /// Per seed, the first `epochs` rows of run `key`.
    fn rows(&self, key: &RunKey, epochs: usize) -> Vec<&[EpochRow]> {
        self.seeds
            .iter()
            .map(|s| {
                let rows = &s.run(key).rows;
                &rows[..epochs.min(rows.len())]
            })
            .collect()
    }

    /// Per seed, the greedy return after each of the first `epochs` epochs of run `key`.
    fn returns(&self, key: &RunKey, epochs: usize) -> Vec<Vec<f64>> {
        self.rows(key, epochs)
            .iter()
            .map(|rows| rows.iter().map(|r| r.policy.ret.mean).collect())
            .collect()
    }

    /// Per seed, the greedy returns of run `key`'s first `epochs` epochs, after writing its
    /// rows into `csv` (after `prefix` columns).
    fn curves(&self, csv: &mut String, prefix: &str, key: &RunKey, epochs: usize) -> Vec<Vec<f64>> {
        curve_lines(csv, prefix, self.seeds, &self.rows(key, epochs));
        self.returns(key, epochs)
    }

    /// The online DQN agent's figures on `task` per seed.
    fn online(&self, task: &str, episodes: usize) -> Vec<PolicyMetrics> {
        self.seeds
            .iter()
            .map(|s| *s.reference(task, episodes))
            .collect()
    }

    fn heuristics(&self, task: &str, episodes: usize) -> &HeuristicRef {
        self.heuristics
            .iter()
            .find(|h| h.task == task && h.episodes == episodes)
            .expect("the plan adds heuristics wherever it adds a reference")
    }

    fn unseen_refs(&self) -> Refs {
        let episodes = self.config.learner.eval_episodes;
        Refs::new(
            self.config,
            &self.online(&self.reproduce.unseen_task, episodes),
            &[self.heuristics(&self.reproduce.unseen_task, episodes)],
        )
    }

    /// The planner in the world each seed's `shots` shots fit, over `tasks` (their mean per seed).
    fn model_planner(&self, tasks: &[&str], shots: usize, episodes: usize) -> ModelPlanner {
        let keys: Vec<ModelPlannerKey> = (tasks.iter())
            .map(|&task| ModelPlannerKey {
                task: task.to_string(),
                shots,
                episodes,
            })
            .collect();
        let mut why = None;
        let per_seed = (self.seeds.iter())
            .map(|s| {
                let planned = keys.iter().map(|k| s.model_planner(k).as_ref());
                let planned: Result<Vec<&PolicyMetrics>, _> = planned.collect();
                planned
                    .map_err(|e| why = why.clone().or(Some(e.clone())))
                    .ok()
                    .map(|ms| ModelPlanner::mean(&ms))
            })
            .collect();
        ModelPlanner {
            keys,
            per_seed,
            why,
        }
    }

    fn seeds_note(&self) -> String {
        match self.seeds.len() {
            1 => "1 seed".into(),
            n => format!("{n} seeds"),
        }
    }
}

/// A figure's model-based section's reference: the planner in the world each seed's shots fit.
struct ModelPlanner {
    keys: Vec<ModelPlannerKey>,
    /// Per seed, (return, AoI, power, outages) averaged over the tasks; `None` where the seed's
    /// shots of some task fit no world.
    per_seed: Vec<Option<[f64; 4]>>,
    /// The first reason a seed's shots fit no world.
    why: Option<String>,
}

impl ModelPlanner {
    fn mean(metrics: &[&PolicyMetrics]) -> [f64; 4] {
        let n = metrics.len() as f64;
        let sum =
            |pick: fn(&PolicyMetrics) -> f64| metrics.iter().map(|m| pick(m)).sum::<f64>() / n;
        [
            sum(|m| m.ret.mean),
            sum(|m| m.aoi.mean),
            sum(|m| m.power_mw.mean),
            sum(|m| m.outages.mean),
        ]
    }

    /// Over the seeds whose shots fit a world, metric `i` (0 return, 1 AoI, 2 power, 3
    /// outages); `None` where no seed's did.
    fn estimate(&self, i: usize) -> Option<Estimate> {
        let fitted: Vec<f64> = self.per_seed.iter().flatten().map(|m| m[i]).collect();
        (!fitted.is_empty()).then(|| est(fitted))
    }

    fn ret(&self) -> Option<Estimate> {
        self.estimate(0)
    }

    /// Its dashed line in a chart of returns / 100.
    fn line(&self) -> Option<Reference> {
        self.ret().map(|r| Reference {
            label: MODEL_PLANNER.into(),
            value: r.mean / 100.0,
        })
    }

    /// What the section says when some seed's shots fit no world; empty when every seed's did.
    fn note(&self) -> String {
        let unfitted = self.per_seed.iter().filter(|m| m.is_none()).count();
        match &self.why {
            Some(why) if unfitted > 0 => format!(
                "\n{}, {} shots: on {unfitted} of {} seeds {NO_FITTED_WORLD}; here: {why}.\n",
                joined(self.keys.iter().map(|k| format!("`{}`", k.task)), ", "),
                self.keys.first().map_or(0, |k| k.shots),
                self.per_seed.len()
            ),
            _ => String::new(),
        }
    }

    /// `model_planner.csv`'s lines: one per task and seed, its metrics or none where the seed's shots
    /// fit no world.
    fn csv_lines(&self, ctx: &Context, csv: &mut String) {
        for key in &self.keys {
            for seed in ctx.seeds {
                let cells = match seed.model_planner(key) {
                    Ok(m) => format!(
                        "{},{},{},{},yes",
                        m.ret.mean, m.aoi.mean, m.power_mw.mean, m.outages.mean
                    ),
                    // Why is in the summary's note.
                    Err(_) => ",,,,no".to_string(),
                };
                let _ = writeln!(csv, "{},{},{},{cells}", key.task, key.shots, seed.seed);
            }
        }
    }
}

/// Writes `model_planner.csv` of a figure's model planners.
fn write_model_planner_csv(
    ctx: &Context,
    dir: &Path,
    planners: &[&ModelPlanner],
) -> Result<(), ReproduceError> {
    let mut csv = String::from("task,shots,seed,return,aoi,power_mw,outages,fitted_world\n");
    for planner in planners {
        planner.csv_lines(ctx, &mut csv);
    }
    Ok(write_file(&dir.join("model_planner.csv"), &csv)?)
}

/// A method's label in a chart's legend, with its section where it is model-based.
fn chart_label(method: Method) -> String {
    match method.model_based() {
        true => format!("{} (model-based)", method.label()),
        false => method.label(),
    }
}

/// The model-based section's title row of a table of `columns` cells after the method's.
fn model_based_row(columns: usize) -> String {
    format!("| *{MODEL_BASED}* |{}\n", " |".repeat(columns))
}

/// The planner's return among `heuristics`, if it was measured.
fn planner_of(heuristics: &[(&str, f64)]) -> Option<f64> {
    let planner = PolicySpec::Planner.to_string();
    (heuristics.iter().find(|(n, _)| *n == planner))
        .map(|&(_, p)| p)
        .filter(|p| p.is_finite())
}

/// Reference levels of a figure, averaged over seeds (and over tasks for figure 9).
struct Refs {
    online: Estimate,
    online_outages: Estimate,
    random: f64,
    /// (name, return) of each heuristic.
    heuristics: Vec<(&'static str, f64)>,
    /// The planner's return, where it was measured: what every gap is taken from.
    planner: Option<f64>,
    /// Share of each dataset the online agent collected while still exploring.
    exploratory: f64,
    eps_start: f64,
}

impl Refs {
    fn new(config: &Config, online: &[PolicyMetrics], heuristics: &[&HeuristicRef]) -> Refs {
        let mean_over = |name: &str| {
            let rets = heuristics.iter().map(|h| h.ret(name).unwrap_or(f64::NAN));
            rets.sum::<f64>() / heuristics.len() as f64
        };
        let names: Vec<&str> = heuristics
            .first()
            .map(|h| h.policies.iter().map(|(n, _)| *n).collect())
            .unwrap_or_default();
        let heuristics: Vec<_> = names.into_iter().map(|n| (n, mean_over(n))).collect();
        Refs {
            online: Estimate::from_samples(online.iter().map(|m| m.ret.mean)),
            online_outages: Estimate::from_samples(online.iter().map(|m| m.outages.mean)),
            random: mean_over("random"),
            planner: planner_of(&heuristics),
            heuristics,
            exploratory: exploratory_share(config),
            eps_start: config.collect.dqn.eps_start,
        }
    }

    /// `value` with its gap to the planner (`stats::gap_to_planner`), marked `*` where above it:
    /// there the planner is a search, not the optimum (docs/MODEL.md section 9).
    fn with_gap(&self, value: Estimate) -> String {
        match self.planner {
            Some(p) => format!("{value:.0} ({})", stats::gap_to_planner(value.mean, p)),
            None => format!("{value:.0}"),
        }
    }

    /// Dashed lines of the returns / 100.
    fn lines(&self) -> Vec<Reference> {
        let online = ("online DQN", self.online.mean);
        (std::iter::once(online).chain(self.heuristics.iter().copied()))
            .map(|(n, v)| Reference {
                label: n.into(),
                value: v / 100.0,
            })
            .collect()
    }

    /// Why methods that should end above the online agent (or learn at all) do not, from their
    /// (label, final return); those that fall short in the same way share one sentence.
    fn shortfall(&self, finals: &[(&str, f64)]) -> String {
        let listed = |pick: &dyn Fn(f64) -> bool| {
            let picked: Vec<String> = finals
                .iter()
                .filter(|(_, ret)| pick(*ret))
                .map(|(label, ret)| format!("{label} ({ret:.0})"))
                .collect();
            let verb = if picked.len() == 1 { "ends" } else { "end" };
            (picked.join(" and "), verb)
        };
        let mut why = Vec::new();
        let (below_random, verb) = listed(&|ret| ret < self.random);
        // Exploring steps are the one cause measured (docs/EXPERIMENTS.md); blamed only when they
        // make up a real part of the shots.
        if !below_random.is_empty() && self.exploratory >= 0.25 {
            why.push(format!(
                "{below_random} {verb} below the uniform random policy ({:.0}): nothing useful is learned \
                 from these shots, {:.0}% of which the online agent took while epsilon still fell from {} \
                 (docs/EXPERIMENTS.md: the same code learns from near-greedy shots)",
                self.random,
                100.0 * self.exploratory,
                self.eps_start
            ));
        } else if !below_random.is_empty() {
            why.push(format!(
                "{below_random} {verb} below the uniform random policy ({:.0}) although only {:.0}% of \
                 these shots were taken while epsilon still fell: near-greedy data is not enough here, \
                 and we have not isolated why",
                self.random,
                100.0 * self.exploratory,
            ));
        }
        let (below_online, verb) = listed(&|ret| ret >= self.random && ret < self.online.mean);
        if !below_online.is_empty() {
            why.push(format!(
                "{below_online} {verb} above the random policy's {:.0} but below the online DQN agent \
                 that made the data ({:.0})",
                self.random, self.online.mean
            ));
        }
        why.join("; ")
    }
}

/// The share of a dataset's transitions that its online DQN agent took before epsilon reached its
/// final value: the dataset is sampled uniformly from the replay buffer, which holds the last
/// `min(dqn_steps, replay_capacity)` steps, and epsilon falls until `learning_starts +
/// eps_decay_steps` (`actors/src/policy/dqn_online.rs`).
fn exploratory_share(config: &Config) -> f64 {
    let c = &config.collect;
    let held = c.dqn.sampled_window().max(1);
    let first_held = c.dqn.steps.saturating_sub(held);
    let decaying_until = c.dqn.learning_starts + c.dqn.eps_decay_steps;
    decaying_until.saturating_sub(first_held).min(held) as f64 / held as f64
}

/// `items` written out, `sep` between them.
fn joined<T: std::fmt::Display>(items: impl IntoIterator<Item = T>, sep: &str) -> String {
    let items: Vec<String> = items.into_iter().map(|i| i.to_string()).collect();
    items.join(sep)
}

/// Per method, one estimate per column of a figure's table (shot counts, task counts).
type MethodValues = Vec<(Method, Vec<Estimate>)>;

/// `method`'s values in `rows`; every figure's rows hold the methods its claims read.
fn of_method<T>(rows: &[(Method, T)], method: Method) -> &T {
    let row = rows.iter().find(|(m, _)| *m == method);
    &row.expect("a figure's rows hold the methods its claims read")
        .1
}

/// A markdown table: one row per method, one column per entry of `columns`, each return with its
/// gap to the planner; the model-based methods in a section of their own, ending with
/// `model_planner` (one value per column, `None` where no seed's shots fit a world).
fn method_table(
    columns: &[String],
    rows: &MethodValues,
    refs: &Refs,
    model_planner: &[Option<Estimate>],
) -> String {
    let mut table = format!(
        "| method | {} |\n| --- |{}\n",
        columns.join(" | "),
        " --- |".repeat(columns.len())
    );
    let (model_free, model_based): (Vec<_>, Vec<_>) =
        rows.iter().partition(|(m, _)| !m.model_based());
    let line =
        |table: &mut String, label: String, values: &mut dyn Iterator<Item = Option<Estimate>>| {
            let cells = values.map(|v| v.map_or("-".into(), |v| refs.with_gap(v)));
            let _ = writeln!(table, "| {label} | {} |", joined(cells, " | "));
        };
    for (method, values) in &model_free {
        line(
            &mut table,
            method.label(),
            &mut values.iter().map(|&v| Some(v)),
        );
    }
    if !model_based.is_empty() || !model_planner.is_empty() {
        table.push_str(&model_based_row(columns.len()));
    }
    for (method, values) in &model_based {
        line(
            &mut table,
            method.label(),
            &mut values.iter().map(|&v| Some(v)),
        );
    }
    if !model_planner.is_empty() {
        line(
            &mut table,
            MODEL_PLANNER.into(),
            &mut model_planner.iter().copied(),
        );
    }
    table
}

fn est(samples: impl IntoIterator<Item = f64>) -> Estimate {
    Estimate::from_samples(samples)
}

/// The final return of runs over seeds.
fn finals(runs: &[Vec<f64>]) -> Estimate {
    est(runs.iter().map(|r| final_return(r)))
}

/// A series over seeds of `runs`, one point per epoch (from 1).
fn series(label: String, runs: &[Vec<f64>]) -> Series {
    let epochs = runs.iter().map(Vec::len).max().unwrap_or(0);
    let x = (1..=epochs).map(|e| e as f64).collect();
    Series {
        label,
        band: Band::from_runs(x, runs),
    }
}

/// A series of returns / 100 over seeds.
fn return_series(label: String, runs: &[Vec<f64>]) -> Series {
    let scaled: Vec<Vec<f64>> = runs
        .iter()
        .map(|r| r.iter().map(|v| v / 100.0).collect())
        .collect();
    series(label, &scaled)
}

/// A chart of greedy returns / 100 per epoch.
fn line_chart(
    path: &Path,
    title: &str,
    series: &[Series],
    references: &[Reference],
) -> Result<(), ReproduceError> {
    let chart = LineChart {
        title,
        x_label: "epoch",
        y_label: "greedy return / 100",
        series,
        references,
        floor: None,
    };
    Ok(plot::line_chart(path, &chart)?)
}

/// One line per method, seed and epoch of `rows`, after `prefix` columns.
fn curve_lines(csv: &mut String, prefix: &str, seeds: &[SeedResult], rows: &[&[EpochRow]]) {
    for (seed, rows) in seeds.iter().zip(rows) {
        for row in rows.iter() {
            let p = &row.policy;
            let _ = writeln!(
                csv,
                "{prefix},{},{},{},{},{},{},{}",
                seed.seed,
                row.epoch,
                p.ret.mean,
                p.ret.ci95,
                p.aoi.mean,
                p.power_mw.mean,
                p.outages.mean
            );
        }
    }
}

const CURVE_COLUMNS: &str = "seed,epoch,return,return_ci95,aoi,power_mw,outages";

/// A figure's section: its body, the footnote of the `*` mark if any return carries it, and its
/// claims' table.
fn finish(mut body: String, claims: Vec<Claim>) -> Result<Section, ReproduceError> {
    let above = stats::ABOVE_PLANNER;
    if body.contains(&format!("%{above})")) {
        let _ = writeln!(
            body,
            "\n{above} above the planner: there the planner is a search, not the optimum \
             (docs/MODEL.md section 9)."
        );
    }
    let _ = writeln!(body, "\n## Claims\n");
    body.push_str(&claims::table(&claims));
    Ok(Section { body, claims })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn estimate(mean: f64) -> Estimate {
        Estimate { mean, ci95: 0.0 }
    }

    /// References of an online agent at -9000, the random policy at -13000 and `heuristics`.
    fn refs(heuristics: Vec<(&'static str, f64)>) -> Refs {
        Refs {
            online: estimate(-9000.0),
            online_outages: estimate(0.0),
            random: -13000.0,
            planner: planner_of(&heuristics),
            heuristics,
            exploratory: 0.55,
            eps_start: 1.0,
        }
    }

    #[test]
    fn a_return_above_the_planner_is_marked_and_its_mark_explained() {
        let refs = refs(vec![(PolicySpec::Planner.to_string().leak(), -7000.0)]);
        assert_eq!(refs.with_gap(estimate(-7700.0)), "-7700 ± 0 (-10.0%)");
        let above = refs.with_gap(estimate(-6930.0));
        assert_eq!(above, "-6930 ± 0 (+1.0%*)");
        let footnote = "* above the planner: there the planner is a search";
        let below = finish(
            format!("| CQL | {} |\n", refs.with_gap(estimate(-7700.0))),
            vec![],
        );
        assert!(!below.unwrap().body.contains(footnote));
        let marked = finish(format!("| CQL | {above} |\n"), vec![]).unwrap().body;
        assert!(marked.contains(footnote), "{marked}");
    }

    #[test]
    fn shortfalls_of_the_same_kind_share_one_sentence() {
        let refs = refs(vec![]);
        let both = refs.shortfall(&[("CQL-MAML", -36000.0), ("CQL", -32000.0)]);
        assert_eq!(
            both.matches("below the uniform random policy").count(),
            1,
            "{both}"
        );
        assert!(
            both.starts_with("CQL-MAML (-36000) and CQL (-32000) end below"),
            "{both}"
        );
        assert!(both.contains("55%"), "{both}");
        let mixed = refs.shortfall(&[("CQL-MAML", -10000.0), ("CQL", -32000.0)]);
        assert!(
            mixed.starts_with("CQL (-32000) ends below the uniform random"),
            "{mixed}"
        );
        assert!(
            mixed.contains("; CQL-MAML (-10000) ends above the random policy's -13000 but below"),
            "{mixed}"
        );
        assert_eq!(refs.shortfall(&[("CQL-MAML", -8000.0)]), "");
        let greedy_shots = Refs {
            exploratory: 0.0,
            ..refs
        };
        let not_the_data = greedy_shots.shortfall(&[("CQL-MAML", -20000.0)]);
        assert!(
            not_the_data.contains("although only 0% of these shots")
                && !not_the_data.contains("docs/EXPERIMENTS.md"),
            "{not_the_data}"
        );
    }

    #[test]
    fn exploratory_share_counts_the_buffer_steps_before_epsilon_settles() {
        let mut config = Config::default();
        let c = &mut config.collect;
        (
            c.dqn.steps,
            c.dqn.replay_capacity,
            c.dqn.learning_starts,
            c.dqn.eps_decay_steps,
        ) = (10_000, 10_000, 500, 5_000);
        assert!((exploratory_share(&config) - 0.55).abs() < 1e-12);
        // A buffer of the last 500 steps holds none of them.
        config.collect.dqn.replay_capacity = 500;
        assert_eq!(exploratory_share(&config), 0.0);
        // Still decaying at the end: all of them.
        config.collect.dqn.eps_decay_steps = 20_000;
        assert_eq!(exploratory_share(&config), 1.0);
    }
}
