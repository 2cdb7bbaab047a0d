//! Figure 4: CQL-MAML's meta-training, its adapted returns beside w0's zero-shot ones and the
//! online agents'.

use super::*;
use uavmeta_meta::meta_train::Evaluation;

/// Figure 4: CQL-MAML's meta-loss, and the tasks' returns per evaluated meta-epoch after
/// adaptation (4b) and zero-shot (4c).
pub(super) fn meta_training(ctx: &Context, dir: &Path) -> Result<Section, ReproduceError> {
    let r = ctx.reproduce;
    let key = InitKey {
        kind: W0,
        tasks: r.meta_tasks,
    };
    let tasks: Vec<&TaskConfig> = crate::runs::meta_train_tasks(ctx.config, r.meta_tasks).collect();
    let curves: Vec<(u64, &MetaCurve)> = ctx
        .seeds
        .iter()
        .map(|s| (s.seed, s.meta_curve(key)))
        .collect();
    write_csvs(&curves, &tasks, dir)?;
    let losses: Vec<Vec<f64>> = curves.iter().map(|(_, c)| c.meta_loss.clone()).collect();
    plot_loss(&losses, dir)?;
    for panel in [ADAPTED, ZERO_SHOT] {
        plot_returns(&curves, &tasks, &panel, dir)?;
    }
    Ok(Section {
        body: summary(ctx, &curves, &losses, &tasks),
        claims: Vec::new(),
    })
}

/// Which of an evaluation's returns a panel of figure 4 shows.
struct Panel {
    file: &'static str,
    title: &'static str,
    pick: fn(&Evaluation) -> &Vec<f64>,
}

const ADAPTED: Panel = Panel {
    file: "fig4b_returns.png",
    title: "Figure 4b: greedy return / 100 after adaptation, per meta-train task",
    pick: |e| &e.adapted,
};

const ZERO_SHOT: Panel = Panel {
    file: "fig4c_zero_shot.png",
    title: "Figure 4c: w0's greedy return / 100 with no adaptation, per meta-train task",
    pick: |e| &e.zero_shot,
};

/// Per seed, task `i`'s returns / 100 (those `pick` takes) at each evaluated meta-epoch.
fn per_task(
    curves: &[(u64, &MetaCurve)],
    i: usize,
    pick: fn(&Evaluation) -> &Vec<f64>,
) -> Vec<Vec<f64>> {
    curves
        .iter()
        .map(|(_, c)| {
            c.evaluations
                .iter()
                .map(|(_, ev)| pick(ev)[i] / 100.0)
                .collect()
        })
        .collect()
}

/// Figure 4a's and 4b's CSV files.
fn write_csvs(
    curves: &[(u64, &MetaCurve)],
    tasks: &[&TaskConfig],
    dir: &Path,
) -> Result<(), ReproduceError> {
    let mut loss_csv = String::from("seed,meta_epoch,meta_loss\n");
    let mut ret_csv = String::from("seed,meta_epoch,task,return,zero_shot\n");
    for (seed, curve) in curves {
        for (e, loss) in curve.meta_loss.iter().enumerate() {
            let _ = writeln!(loss_csv, "{seed},{},{loss}", e + 1);
        }
        for (epoch, ev) in &curve.evaluations {
            for (i, task) in tasks.iter().enumerate() {
                let (adapted, zero_shot) = (ev.adapted[i], ev.zero_shot[i]);
                let _ = writeln!(
                    ret_csv,
                    "{seed},{epoch},{},{adapted},{zero_shot}",
                    task.name
                );
            }
        }
    }
    write_file(&dir.join("fig4a_meta_loss.csv"), &loss_csv)?;
    Ok(write_file(&dir.join("fig4b_returns.csv"), &ret_csv)?)
}

/// Figure 4a: the meta-loss per meta-epoch, one run per seed.
fn plot_loss(losses: &[Vec<f64>], dir: &Path) -> Result<(), ReproduceError> {
    let chart = LineChart {
        title: "Figure 4a: CQL-MAML meta-training loss",
        x_label: "meta-epoch",
        y_label: "meta-loss (eq. 15)",
        series: &[series("meta-loss".into(), losses)],
        references: &[],
        // TD errors squared plus eq. 8's log-sum-exp gap: never negative.
        floor: Some(0.0),
    };
    Ok(plot::line_chart(&dir.join("fig4a_meta_loss.png"), &chart)?)
}

/// Figure 4b or 4c: each meta-train task's return at the evaluated meta-epochs.
fn plot_returns(
    curves: &[(u64, &MetaCurve)],
    tasks: &[&TaskConfig],
    panel: &Panel,
    dir: &Path,
) -> Result<(), ReproduceError> {
    let evaluated: Vec<f64> = curves
        .first()
        .map(|(_, c)| c.evaluations.iter().map(|(e, _)| *e as f64).collect())
        .unwrap_or_default();
    let series: Vec<Series> = tasks
        .iter()
        .enumerate()
        .map(|(i, t)| Series {
            label: t.name.clone(),
            band: Band::from_runs(evaluated.clone(), &per_task(curves, i, panel.pick)),
        })
        .collect();
    let chart = LineChart {
        title: panel.title,
        x_label: "meta-epoch",
        y_label: "return / 100",
        series: &series,
        references: &[],
        floor: None,
    };
    Ok(plot::line_chart(&dir.join(panel.file), &chart)?)
}

/// The summary's body: the run, the meta-loss's first and last values, and a table of each
/// task's returns against its online agent's.
fn summary(
    ctx: &Context,
    curves: &[(u64, &MetaCurve)],
    losses: &[Vec<f64>],
    tasks: &[&TaskConfig],
) -> String {
    let r = ctx.reproduce;
    let episodes = ctx.config.learner.eval_episodes;
    let mut body = format!(
        "CQL-MAML meta-trained on the first {} meta-train tasks for {} meta-epochs, {}; every {} \
         meta-epochs each task's greedy return over {episodes} episodes, after adaptation (eq. 14, \
         the mean of {} adaptations on fresh support shots) and with none (w0 zero-shot). docs/MODEL.md \
         section 6 states no claim for this figure.\n\n",
        r.meta_tasks,
        ctx.config.meta.meta_epochs,
        ctx.seeds_note(),
        r.meta_eval_every,
        ctx.config.meta.eval_adaptations,
    );
    let first = est(losses.iter().filter_map(|l| l.first().copied()));
    let last = est(losses.iter().filter_map(|l| l.last().copied()));
    let _ = writeln!(
        body,
        "Meta-loss: {first:.4} at the first meta-epoch, {last:.4} at the last.\n"
    );
    let _ = writeln!(
        body,
        "| task | online agent | adapted, first evaluation | adapted, last evaluation | w0 zero-shot, last evaluation |\n\
         | --- | --- | --- | --- | --- |"
    );
    for (i, task) in tasks.iter().enumerate() {
        let (adapted, zero_shot) = (
            per_task(curves, i, ADAPTED.pick),
            per_task(curves, i, ZERO_SHOT.pick),
        );
        let at = |runs: &[Vec<f64>], end: fn(&Vec<f64>) -> Option<&f64>| {
            est(runs.iter().filter_map(|r| end(r).map(|v| v * 100.0)))
        };
        let online = est(ctx.online(&task.name, episodes).iter().map(|m| m.ret.mean));
        let _ = writeln!(
            body,
            "| {} | {online:.0} | {:.0} | {:.0} | {:.0} |",
            task.name,
            at(&adapted, |r| r.first()),
            at(&adapted, |r| r.last()),
            at(&zero_shot, |r| r.last()),
        );
    }
    body
}
