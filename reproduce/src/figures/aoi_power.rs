//! Figure 8: AoI and power after 50 epochs, beside the paper's values.

use super::*;

/// The paper's figure 8 (AoI, mW) for CQL-MAML, online DQN and CQL at lambda = 300, epoch 50.
const PAPER_FIG8: [(&str, f64, f64); 3] = [
    ("CQL-MAML", 6.0, 1.6),
    ("online DQN", 7.0, 2.2),
    ("CQL", 28.0, 6.0),
];

/// The noise power of the paper's milliwatt figures (docs/MODEL.md section 1).
const PAPER_NOISE_DBM: f64 = -90.0;

/// (name, AoI, power) of a method over seeds.
type Measured<'a> = (&'a str, Estimate, Estimate);

/// Each method measured, then the heuristics, with the paper's (AoI, mW) where it has them.
fn rows<'a>(
    measured: &'a [Measured],
    heuristics: &'a [(&str, PolicyMetrics)],
) -> impl Iterator<Item = (&'a str, Estimate, Estimate, Option<(f64, f64)>)> {
    let paper = |i: usize| PAPER_FIG8.get(i).map(|&(_, aoi, mw)| (aoi, mw));
    (measured.iter().enumerate())
        .map(move |(i, &(name, aoi, power))| (name, aoi, power, paper(i)))
        .chain((heuristics.iter()).map(|(name, m)| (*name, m.aoi, m.power_mw, None)))
}

/// Figure 8: AoI and power at epoch `aoi_power_epoch`.
pub(super) fn aoi_power(ctx: &Context, dir: &Path) -> Result<Section, ReproduceError> {
    let c = ctx.config;
    let r = ctx.reproduce;
    let epoch = r.aoi_power_epoch;
    let at_epoch = |m: Method| -> Vec<PolicyMetrics> {
        ctx.rows(&unseen_key(c, r, m, r.main_shots, r.meta_tasks), epoch)
            .iter()
            .filter_map(|rows| rows.last().map(|row| row.policy))
            .collect()
    };
    let online = ctx.online(&r.unseen_task, c.learner.eval_episodes);
    let paper_three = [
        (Method::CQL_MAML.label(), at_epoch(Method::CQL_MAML)),
        (Method::OnlineDqn.label(), online),
        (Method::CQL.label(), at_epoch(Method::CQL)),
    ];
    // Not in the paper: the other compared methods after its three, with no paper figures, the
    // model-based ones last, then the planner in the fitted world.
    let others = (compared(c).into_iter()).filter(|m| ![Method::CQL_MAML, Method::CQL].contains(m));
    let (model_free, model_based): (Vec<Method>, Vec<Method>) =
        others.partition(|m| !m.model_based());
    let mut learned: Vec<(String, Vec<PolicyMetrics>)> = (paper_three.into_iter())
        .chain(model_free.into_iter().map(|m| (m.label(), at_epoch(m))))
        .collect();
    let model_free_rows = learned.len();
    learned.extend(model_based.into_iter().map(|m| (m.label(), at_epoch(m))));
    let planner = ModelPlannerKey {
        task: r.unseen_task.clone(),
        shots: r.main_shots,
        episodes: c.learner.eval_episodes,
    };
    // Where every seed's shots fit a world (figure 5's table says where they do not).
    let planned: Option<Vec<PolicyMetrics>> = (ctx.seeds.iter())
        .map(|s| s.model_planner(&planner).as_ref().ok().copied())
        .collect();
    learned.extend(planned.map(|p| (MODEL_PLANNER.to_string(), p)));
    let heuristics = &ctx
        .heuristics(&r.unseen_task, c.learner.eval_episodes)
        .policies;
    write_bars_csv(ctx, &learned, heuristics, dir)?;

    // The paper's milliwatts are on a noise floor of -90 dBm; power scales with the noise power.
    let paper_scale = 10f64.powf((PAPER_NOISE_DBM - c.world.noise_dbm) / 10.0);
    let measured: Vec<Measured> = learned
        .iter()
        .map(|(name, per_seed)| {
            (
                name.as_str(),
                est(per_seed.iter().map(|m| m.aoi.mean)),
                est(per_seed.iter().map(|m| m.power_mw.mean)),
            )
        })
        .collect();
    let (aoi_bars, power_bars) = bars(&measured, heuristics, paper_scale);
    plot::bar_chart(
        &dir.join("fig8a_aoi.png"),
        &format!("Figure 8a: AoI on `{}` after {epoch} epochs", r.unseen_task),
        "mean AoI",
        &aoi_bars,
    )?;
    plot::bar_chart(
        &dir.join("fig8b_power.png"),
        &format!(
            "Figure 8b: power on `{}` after {epoch} epochs",
            r.unseen_task
        ),
        "mean power (mW)",
        &power_bars,
    )?;
    let body = summary_table(ctx, &measured, model_free_rows, heuristics, paper_scale);
    finish(body, vec![order_claim(&measured)])
}

/// `bars.csv`: AoI and power per method and seed, then the heuristics'.
fn write_bars_csv(
    ctx: &Context,
    learned: &[(String, Vec<PolicyMetrics>)],
    heuristics: &[(&str, PolicyMetrics)],
    dir: &Path,
) -> Result<(), ReproduceError> {
    let mut csv = String::from("method,seed,aoi,power_mw\n");
    for (name, per_seed) in learned {
        for (seed, m) in ctx.seeds.iter().zip(per_seed) {
            let _ = writeln!(
                csv,
                "{name},{},{},{}",
                seed.seed, m.aoi.mean, m.power_mw.mean
            );
        }
    }
    for (name, m) in heuristics {
        let _ = writeln!(csv, "{name},,{},{}", m.aoi.mean, m.power_mw.mean);
    }
    Ok(write_file(&dir.join("bars.csv"), &csv)?)
}

/// The AoI and power bars: each method measured, beside the paper's figure where it has one,
/// then the heuristics.
fn bars(
    measured: &[Measured],
    heuristics: &[(&str, PolicyMetrics)],
    paper_scale: f64,
) -> (Vec<Bar>, Vec<Bar>) {
    let bar = |group: &str, label: &str, value| Bar {
        group: group.to_string(),
        label: label.into(),
        value,
    };
    let paper = |mean| Estimate { mean, ci95: 0.0 };
    let (mut aoi_bars, mut power_bars) = (Vec::new(), Vec::new());
    for (name, aoi, power, paper_values) in rows(measured, heuristics) {
        aoi_bars.push(bar(name, "measured", aoi));
        power_bars.push(bar(name, "measured", power));
        if let Some((paper_aoi, paper_mw)) = paper_values {
            aoi_bars.push(bar(name, "paper", paper(paper_aoi)));
            let rescaled = paper(paper_mw / paper_scale);
            power_bars.push(bar(name, "paper, on our noise floor", rescaled));
        }
    }
    (aoi_bars, power_bars)
}

/// The summary's opening and its table, beside the paper's values; the rows of `measured` after
/// the first `model_free` in the model-based section.
fn summary_table(
    ctx: &Context,
    measured: &[Measured],
    model_free: usize,
    heuristics: &[(&str, PolicyMetrics)],
    paper_scale: f64,
) -> String {
    let c = ctx.config;
    let r = ctx.reproduce;
    let mut body = format!(
        "AoI and power of the greedy policies on `{}` after {} fine-tuning epochs on {} shots, {}. \
         Power scales with the noise power: our world uses noise_dbm = {}, the paper's milliwatts \
         correspond to {PAPER_NOISE_DBM} dBm (docs/MODEL.md section 1), so its figures are {paper_scale:.3}x ours \
         for the same policy; the chart and table show them rescaled to our noise floor.\n\n\
         | method | AoI | paper AoI | power (mW) | paper power, rescaled (mW) |\n| --- | --- | --- | --- | --- |\n",
        r.unseen_task,
        r.aoi_power_epoch,
        r.main_shots,
        ctx.seeds_note(),
        c.world.noise_dbm
    );
    for (i, (name, aoi, power, paper)) in rows(measured, heuristics).enumerate() {
        if i == model_free && model_free < measured.len() {
            body.push_str(&model_based_row(4));
        }
        if i == measured.len() && model_free < measured.len() {
            body.push_str("| *references* | | | | |\n");
        }
        let _ = match paper {
            Some((paper_aoi, paper_mw)) => writeln!(
                body,
                "| {name} | {aoi:.2} | {paper_aoi} | {power:.3} | {:.3} |",
                paper_mw / paper_scale
            ),
            None => writeln!(body, "| {name} | {aoi:.2} | | {power:.3} | |"),
        };
    }
    body
}

/// The claim's content is its ordering: CQL-MAML below online DQN below CQL, in both metrics.
fn order_claim(measured: &[Measured]) -> Claim {
    // (metric, lower, higher, their means): the paper has `lower` below `higher`.
    let orders: Vec<(&str, usize, usize, f64, f64)> = [(0, 1), (1, 2)]
        .into_iter()
        .flat_map(|(lo, hi)| {
            [
                ("AoI", lo, hi, measured[lo].1.mean, measured[hi].1.mean),
                ("power", lo, hi, measured[lo].2.mean, measured[hi].2.mean),
            ]
        })
        .collect();
    let held = orders.iter().filter(|o| o.3 < o.4).count();
    Claim::new(
        "8",
        "lambda = 300 after 50 epochs: CQL-MAML AoI 6 / 1.6 mW, online DQN 7 / 2.2 mW, CQL 28 / 6 mW (CQL-MAML best, CQL worst in both)",
        joined(measured.iter().map(|(n, a, p)| format!("{n} AoI {a:.2}, {p:.3} mW")), "; "),
        Verdict::share(held, orders.len()),
        || {
            let broken: Vec<String> = orders
                .iter()
                .filter(|o| o.3 >= o.4)
                .map(|&(metric, lo, hi, lo_mean, hi_mean)| {
                    format!(
                        "{metric} of {} ({lo_mean:.3}) is not below {}'s ({hi_mean:.3})",
                        measured[lo].0, measured[hi].0
                    )
                })
                .collect();
            format!("the paper's order does not hold: {}", broken.join("; "))
        },
    )
}
