//! Figure 7: CQL-MAML meta-trained on 2 to 10 tasks, and CQL-context trained on as many.

use super::*;

/// Figure 7: CQL-MAML meta-trained on the first n tasks, and CQL-context trained on them.
pub(super) fn tasks(ctx: &Context, dir: &Path) -> Result<Section, ReproduceError> {
    let c = ctx.config;
    let r = ctx.reproduce;
    let epochs = r.tasks_epochs;
    let at = EPOCH_40.min(epochs);
    let refs = ctx.unseen_refs();
    let mut csv = format!("method,tasks,{CURVE_COLUMNS}\n");
    let mut series = Vec::new();
    let mut values = Vec::new();
    let mut context = Vec::new();
    for &n in &r.task_counts {
        for (method, at_n) in [
            (Method::CQL_MAML, &mut values),
            (Method::CQL_CONTEXT, &mut context),
        ] {
            let key = unseen_key(c, r, method, r.main_shots, n);
            let runs = ctx.curves(&mut csv, &format!("{method},{n}"), &key, epochs);
            series.push(return_series(
                format!("{} {n} tasks", method.label()),
                &runs,
            ));
            at_n.push((n, est(runs.iter().map(|r| return_at(r, at)))));
        }
    }
    let cql_key = unseen_key(c, r, Method::CQL, r.main_shots, 0);
    let cql_runs = ctx.curves(&mut csv, "cql,0", &cql_key, epochs);
    series.push(return_series("CQL".into(), &cql_runs));
    let cql = est(cql_runs.iter().map(|r| return_at(r, at)));
    write_file(&dir.join("curves.csv"), &csv)?;
    line_chart(
        &dir.join("fig7.png"),
        &format!("Figure 7: meta-training tasks, `{}`", r.unseen_task),
        &series,
        &refs.lines()[..1],
    )?;

    let mut body = format!(
        "CQL-MAML meta-trained on the first n meta-train tasks (config order: {}), fine-tuned for \
         {epochs} epochs on {} shots of `{}`, {}; \"return at epoch {at}\" is the mean of epochs {}..{at}. \
         CQL-context's encoder and Q-network are trained on the same tasks.\n\n\
         | meta-train tasks | CQL-MAML at epoch {at} | CQL-context at epoch {at} |\n| --- | --- | --- |\n",
        joined(crate::runs::meta_train_tasks(c, usize::MAX).map(|t| &t.name), ", "),
        r.main_shots,
        r.unseen_task,
        ctx.seeds_note(),
        at.saturating_sub(claims::FINAL_EPOCHS) + 1
    );
    for ((n, v), (_, x)) in values.iter().zip(&context) {
        let _ = writeln!(body, "| {n} | {v:.0} | {x:.0} |");
    }
    let _ = writeln!(
        body,
        "| CQL (random init) | {cql:.0} | |\n| online DQN | {:.0} | |",
        refs.online
    );
    let mut found = vec![rising_claim(&values), eight_claim(&values, &refs)];
    found.extend(two_claim(&values, cql, at));
    finish(body, found)
}

/// "n: return; ..." for every task count.
fn listed(values: &[(usize, Estimate)]) -> String {
    joined(values.iter().map(|(n, v)| format!("{n}: {v:.0}")), "; ")
}

/// More meta-training tasks, better: `values` is (tasks, return at epoch 40) in task order.
fn rising_claim(values: &[(usize, Estimate)]) -> Claim {
    let rising = values.windows(2).all(|w| w[1].1.mean > w[0].1.mean);
    let first_to_last = match (values.first(), values.last()) {
        (Some(a), Some(b)) if values.len() > 1 => b.1.mean > a.1.mean,
        _ => false,
    };
    Claim::new(
        "7",
        "More meta-training tasks, better (2, 4, 6, 8, 10)",
        listed(values),
        if values.len() < 2 {
            Verdict::Untested
        } else if rising {
            Verdict::Yes
        } else if first_to_last {
            Verdict::Partly
        } else {
            Verdict::No
        },
        || {
            let falls: Vec<_> = (values.windows(2))
                .filter(|w| w[1].1.mean <= w[0].1.mean)
                .collect();
            let overlap =
                (falls.iter()).all(|w| w[0].1.mean - w[0].1.ci95 <= w[1].1.mean + w[1].1.ci95);
            format!(
                "the return does not rise from {}{}",
                joined(
                    falls
                        .iter()
                        .map(|w| format!("{} -> {} tasks", w[0].0, w[1].0)),
                    ", "
                ),
                if overlap {
                    " (within the seeds' 95% intervals: the differences are noise at this seed count)"
                } else {
                    ""
                }
            )
        },
    )
}

/// At least 8 tasks are needed to beat online DQN within 40 epochs.
fn eight_claim(values: &[(usize, Estimate)], refs: &Refs) -> Claim {
    let beats = |v: &Estimate| v.mean > refs.online.mean;
    let (many, few): (Vec<_>, Vec<_>) = values.iter().partition(|(n, _)| *n >= 8);
    let verdict = if many.is_empty() {
        Verdict::Untested
    } else if !many.iter().all(|(_, v)| beats(v)) {
        Verdict::No
    } else if few.iter().any(|(_, v)| beats(v)) {
        Verdict::Partly
    } else {
        Verdict::Yes
    };
    Claim::new(
        "7",
        "At least 8 tasks are needed to beat online DQN within 40 epochs",
        format!("{}; online DQN {:.0}", listed(values), refs.online),
        verdict,
        || {
            if many.iter().all(|(_, v)| beats(v)) {
                "fewer than 8 tasks beat online DQN too".into()
            } else {
                let best = many
                    .iter()
                    .map(|(_, v)| v.mean)
                    .fold(f64::NEG_INFINITY, f64::max);
                refs.shortfall(&[("CQL-MAML with >= 8 tasks", best)])
            }
        },
    )
}

/// Even the fewest meta-training tasks beat plain CQL at epoch `at`.
fn two_claim(values: &[(usize, Estimate)], cql: Estimate, at: usize) -> Option<Claim> {
    let &(n, fewest) = values.first()?;
    Some(Claim::new(
        "7",
        "Even 2 meta-training tasks beat plain CQL",
        format!("CQL-MAML on {n} tasks {fewest:.0}; CQL {cql:.0} (return at epoch {at})"),
        Verdict::beats(fewest, cql),
        || {
            if fewest.mean > cql.mean {
                "the mean is higher but the 95% intervals overlap".into()
            } else {
                format!("a w0 meta-trained on {n} tasks starts no better than a random init here")
            }
        },
    ))
}
