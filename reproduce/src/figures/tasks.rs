//! Figure 7: every compared method with an init trained on 2 to 10 meta-train tasks.

use super::*;

/// Figure 7: each compared method whose init is trained on the meta-train tasks (w0, CQL-pretrain,
/// CQL-context), trained on the first n of them; the methods from a random init once.
pub(super) fn tasks(ctx: &Context, dir: &Path) -> Result<Section, ReproduceError> {
    let c = ctx.config;
    let r = ctx.reproduce;
    let epochs = r.tasks_epochs;
    let at = EPOCH_40.min(epochs);
    let refs = ctx.unseen_refs();
    let mut csv = format!("method,tasks,{CURVE_COLUMNS}\n");
    // Figure 7 as the paper draws it: CQL-MAML's curves per task count beside CQL's.
    let mut curves = Vec::new();
    // Figure 7b: every method's return at epoch `at` against the task count.
    let mut by_tasks = Vec::new();
    let (mut rows, mut from_random): (MethodValues, MethodValues) = (vec![], vec![]);
    for method in compared(c) {
        let trained = Init::of(method).is_some();
        let counts = if trained {
            r.task_counts.clone()
        } else {
            vec![0]
        };
        let mut values = Vec::new();
        let mut seeds_at: Vec<Vec<f64>> = vec![vec![]; ctx.seeds.len()];
        for &n in &counts {
            let key = unseen_key(c, r, method, r.main_shots, n);
            let runs = ctx.curves(&mut csv, &format!("{method},{n}"), &key, epochs);
            if method == Method::CQL_MAML || method == Method::CQL {
                let label = match n {
                    0 => chart_label(method),
                    n => format!("{} {n} tasks", chart_label(method)),
                };
                curves.push(return_series(label, &runs));
            }
            for (seed, run) in seeds_at.iter_mut().zip(&runs) {
                seed.push(return_at(run, at) / 100.0);
            }
            values.push(est(runs.iter().map(|r| return_at(r, at))));
        }
        if trained {
            let x = counts.iter().map(|&n| n as f64).collect();
            by_tasks.push(Series {
                label: chart_label(method),
                band: Band::from_runs(x, &seeds_at),
            });
            rows.push((method, values));
        } else {
            from_random.push((method, values));
        }
    }
    write_file(&dir.join("curves.csv"), &csv)?;
    let planner = ctx.model_planner(&[&r.unseen_task], r.main_shots, c.learner.eval_episodes);
    write_model_planner_csv(ctx, dir, &[&planner])?;
    line_chart(
        &dir.join("fig7.png"),
        &format!("Figure 7: meta-training tasks, `{}`", r.unseen_task),
        &curves,
        &refs.lines()[..1],
    )?;
    plot_by_tasks(
        &dir.join("fig7b_by_tasks.png"),
        at,
        &by_tasks,
        &from_random,
        &refs,
        &planner,
    )?;

    let mut body = format!(
        "Each method's init (w0, CQL-pretrain's network, CQL-context's encoder and Q-network) trained \
         on the first n meta-train tasks (config order: {}), then fine-tuned for {epochs} epochs on {} \
         shots of `{}`, {}; \"return at epoch {at}\" is the mean of epochs {}..{at}, in brackets its gap to the \
         planner. Figure 7 draws \
         CQL-MAML's curves beside CQL's, as the paper does; figure 7b every method's return at epoch \
         {at} against the number of tasks.\n\n",
        joined(crate::runs::meta_train_tasks(c, usize::MAX).map(|t| &t.name), ", "),
        r.main_shots,
        r.unseen_task,
        ctx.seeds_note(),
        at.saturating_sub(claims::FINAL_EPOCHS) + 1
    );
    let columns: Vec<String> = r.task_counts.iter().map(|n| format!("{n} tasks")).collect();
    // The planner in the fitted world reads no meta-train task: one value for every count.
    let planned = planner
        .ret()
        .map_or(vec![], |p| vec![Some(p); columns.len()]);
    body.push_str(&method_table(&columns, &rows, &refs, &planned));
    let _ = writeln!(
        body,
        "\nFrom a random init (no meta-train tasks), at epoch {at}: {}; online DQN {}.",
        joined(
            from_random
                .iter()
                .map(|(m, v)| format!("{} {}", chart_label(*m), refs.with_gap(v[0]))),
            "; "
        ),
        refs.with_gap(refs.online)
    );
    body.push_str(&planner.note());
    let maml: Vec<(usize, Estimate)> = (r.task_counts.iter().copied())
        .zip(of_method(&rows, Method::CQL_MAML).iter().copied())
        .collect();
    let cql = of_method(&from_random, Method::CQL)[0];
    let mut found = vec![rising_claim(&maml), eight_claim(&maml, &refs)];
    found.extend(two_claim(&maml, cql, at));
    finish(body, found)
}

/// Figure 7b: each method's return at epoch `at` against the task count, the methods from a
/// random init, online DQN and the planner in the fitted world as dashed lines.
fn plot_by_tasks(
    path: &Path,
    at: usize,
    by_tasks: &[Series],
    from_random: &MethodValues,
    refs: &Refs,
    planner: &ModelPlanner,
) -> Result<(), ReproduceError> {
    let random_lines = from_random.iter().map(|(m, v)| Reference {
        label: format!("{} (random init)", chart_label(*m)),
        value: v[0].mean / 100.0,
    });
    let references: Vec<Reference> = (refs.lines().into_iter().take(1))
        .chain(random_lines)
        .chain(planner.line())
        .collect();
    let chart = LineChart {
        title: &format!("Figure 7b: return at epoch {at} by meta-training tasks"),
        x_label: "meta-train tasks",
        y_label: &format!("greedy return / 100 at epoch {at}"),
        series: by_tasks,
        references: &references,
        floor: None,
    };
    Ok(plot::line_chart(path, &chart)?)
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
