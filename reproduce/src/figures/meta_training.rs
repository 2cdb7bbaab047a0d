//! Figure 4: CQL-MAML's meta-training.

use super::*;

/// Figure 4: CQL-MAML's meta-loss and the tasks' adapted returns per meta-epoch.
pub(super) fn meta_training(ctx: &Context, dir: &Path) -> Result<Section, ReproduceError> {
    let r = &ctx.config.reproduce;
    let key = InitKey {
        kind: InitKind::Maml(InnerLoss::Cql),
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
    plot_returns(&curves, &tasks, dir)?;
    Ok(Section {
        body: summary(ctx, &curves, &losses, &tasks),
        claims: Vec::new(),
    })
}

/// Per seed, task `i`'s adapted returns / 100 at each evaluated meta-epoch.
fn per_task(curves: &[(u64, &MetaCurve)], i: usize) -> Vec<Vec<f64>> {
    curves
        .iter()
        .map(|(_, c)| c.returns.iter().map(|(_, r)| r[i] / 100.0).collect())
        .collect()
}

/// Figure 4a's and 4b's CSV files.
fn write_csvs(
    curves: &[(u64, &MetaCurve)],
    tasks: &[&TaskConfig],
    dir: &Path,
) -> Result<(), ReproduceError> {
    let mut loss_csv = String::from("seed,meta_epoch,meta_loss\n");
    let mut ret_csv = String::from("seed,meta_epoch,task,return\n");
    for (seed, curve) in curves {
        for (e, loss) in curve.meta_loss.iter().enumerate() {
            let _ = writeln!(loss_csv, "{seed},{},{loss}", e + 1);
        }
        for (epoch, returns) in &curve.returns {
            for (task, ret) in tasks.iter().zip(returns) {
                let _ = writeln!(ret_csv, "{seed},{epoch},{},{ret}", task.name);
            }
        }
    }
    write_file(&dir.join("fig4a_meta_loss.csv"), &loss_csv)?;
    write_file(&dir.join("fig4b_returns.csv"), &ret_csv)?;
    Ok(())
}

/// Figure 4a: the meta-loss per meta-epoch, one run per seed.
fn plot_loss(losses: &[Vec<f64>], dir: &Path) -> Result<(), ReproduceError> {
    let meta_epochs = losses.iter().map(Vec::len).max().unwrap_or(0);
    plot::line_chart(
        &dir.join("fig4a_meta_loss.png"),
        &LineChart {
            title: "Figure 4a: CQL-MAML meta-training loss",
            x_label: "meta-epoch",
            y_label: "meta-loss (eq. 15)",
            series: &[Series {
                label: "meta-loss".into(),
                band: Band::from_runs(epochs_x(meta_epochs), losses),
            }],
            references: &[],
            // TD errors squared plus eq. 8's log-sum-exp gap: never negative.
            floor: Some(0.0),
        },
    )?;
    Ok(())
}

/// Figure 4b: each meta-train task's adapted return at the evaluated meta-epochs.
fn plot_returns(
    curves: &[(u64, &MetaCurve)],
    tasks: &[&TaskConfig],
    dir: &Path,
) -> Result<(), ReproduceError> {
    let evaluated: Vec<f64> = curves
        .first()
        .map(|(_, c)| c.returns.iter().map(|(e, _)| *e as f64).collect())
        .unwrap_or_default();
    let series: Vec<Series> = tasks
        .iter()
        .enumerate()
        .map(|(i, t)| Series {
            label: t.name.clone(),
            band: Band::from_runs(evaluated.clone(), &per_task(curves, i)),
        })
        .collect();
    plot::line_chart(
        &dir.join("fig4b_returns.png"),
        &LineChart {
            title: "Figure 4b: greedy return / 100 after adaptation, per meta-train task",
            x_label: "meta-epoch",
            y_label: "return / 100",
            series: &series,
            references: &[],
            floor: None,
        },
    )?;
    Ok(())
}

/// The summary's body: the run, the meta-loss's first and last values, and a table of each
/// task's adapted return.
fn summary(
    ctx: &Context,
    curves: &[(u64, &MetaCurve)],
    losses: &[Vec<f64>],
    tasks: &[&TaskConfig],
) -> String {
    let r = &ctx.config.reproduce;
    let mut body = format!(
        "CQL-MAML meta-trained on the first {} meta-train tasks for {} meta-epochs, {}; each task's \
         adapted greedy return evaluated every {} meta-epochs over {} episodes. SPEC section 6 states no \
         claim for this figure.\n\n",
        r.meta_tasks,
        ctx.config.meta.meta_epochs,
        ctx.seeds_note(),
        r.meta_eval_every,
        ctx.config.learner.eval_episodes
    );
    let first = est(losses.iter().filter_map(|l| l.first().copied()));
    let last = est(losses.iter().filter_map(|l| l.last().copied()));
    let _ = writeln!(
        body,
        "Meta-loss: {first:.4} at the first meta-epoch, {last:.4} at the last.\n"
    );
    let _ = writeln!(
        body,
        "| task | adapted return, first evaluation | adapted return, last evaluation |\n| --- | --- | --- |"
    );
    for (i, task) in tasks.iter().enumerate() {
        let runs = per_task(curves, i);
        let at = |pick: fn(&Vec<f64>) -> Option<&f64>| {
            est(runs.iter().filter_map(|r| pick(r).map(|v| v * 100.0)))
        };
        let _ = writeln!(
            body,
            "| {} | {:.0} | {:.0} |",
            task.name,
            at(|r| r.first()),
            at(|r| r.last())
        );
    }
    body
}
