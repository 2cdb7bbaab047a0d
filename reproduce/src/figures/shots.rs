//! Figure 6: every compared method on 100, 300 and 500 shots.

use super::*;

/// "Far more" dependence on the shot count: at least this ratio of spreads.
const FAR_MORE: f64 = 2.0;

/// One shot count's final returns of the two methods the claims compare.
struct Finals {
    shots: usize,
    maml: Estimate,
    cql: Estimate,
}

/// Figure 6: every compared method at each shot count.
pub(super) fn shots(ctx: &Context, dir: &Path) -> Result<Section, ReproduceError> {
    let c = ctx.config;
    let r = ctx.reproduce;
    let epochs = r.convergence_epochs;
    let mut csv = format!("method,shots,{CURVE_COLUMNS}\n");
    let mut series = Vec::new();
    let mut rows: MethodValues = compared(c).into_iter().map(|m| (m, vec![])).collect();
    for &shots in &r.shots {
        for (method, values) in &mut rows {
            let key = unseen_key(c, r, *method, shots, r.meta_tasks);
            let prefix = format!("{},{shots}", method.name());
            let runs = ctx.curves(&mut csv, &prefix, &key, epochs);
            series.push(return_series(
                format!("{} {shots} shots", chart_label(*method)),
                &runs,
            ));
            values.push(finals(&runs));
        }
    }
    write_file(&dir.join("curves.csv"), &csv)?;
    let episodes = c.learner.eval_episodes;
    let planners: Vec<ModelPlanner> = (r.shots.iter())
        .map(|&shots| ctx.model_planner(&[&r.unseen_task], shots, episodes))
        .collect();
    write_model_planner_csv(ctx, dir, &planners.iter().collect::<Vec<_>>())?;
    line_chart(
        &dir.join("fig6.png"),
        &format!("Figure 6: shots of `{}`", r.unseen_task),
        &series,
        &[],
    )?;

    let mut body = format!(
        "Each method fine-tuned for {epochs} epochs on {:?} shots of `{}` (the inits trained on the \
         first {} meta-train tasks), {}. Final return = mean of the last {} epochs; in brackets, its gap to the planner.\n\n",
        r.shots,
        r.unseen_task,
        r.meta_tasks,
        ctx.seeds_note(),
        claims::FINAL_EPOCHS
    );
    let columns: Vec<String> = r.shots.iter().map(|s| format!("{s} shots")).collect();
    let planned: Vec<Option<Estimate>> = planners.iter().map(ModelPlanner::ret).collect();
    let planned = if planned.iter().any(Option::is_some) {
        planned
    } else {
        vec![]
    };
    body.push_str(&method_table(&columns, &rows, &ctx.unseen_refs(), &planned));
    planners.iter().for_each(|p| body.push_str(&p.note()));
    let (maml, cql) = (
        of_method(&rows, Method::CQL_MAML),
        of_method(&rows, Method::CQL),
    );
    let finals_per_size: Vec<Finals> = (r.shots.iter().zip(maml.iter().zip(cql)))
        .map(|(&shots, (&maml, &cql))| Finals { shots, maml, cql })
        .collect();
    let found = vec![
        beats_claim(&finals_per_size),
        spread_claim(&finals_per_size),
    ];
    finish(body, found)
}

/// CQL-MAML beats CQL at every number of shots.
fn beats_claim(finals: &[Finals]) -> Claim {
    let losing: Vec<String> = finals
        .iter()
        .filter(|f| f.maml.mean <= f.cql.mean)
        .map(|f| format!("{} shots: {:.0} vs {:.0}", f.shots, f.maml.mean, f.cql.mean))
        .collect();
    let measured = (finals.iter()).map(|f| format!("{}: {:.0} vs {:.0}", f.shots, f.maml, f.cql));
    Claim::new(
        "6",
        "CQL-MAML beats CQL at every number of shots (100, 300, 500)",
        joined(measured, "; "),
        Verdict::all_of(finals.iter().map(|f| Verdict::beats(f.maml, f.cql))),
        || {
            if losing.is_empty() {
                "CQL-MAML's mean is higher at every size, but the 95% intervals overlap".into()
            } else {
                format!(
                    "the meta-learned init does not help at {}",
                    losing.join(", ")
                )
            }
        },
    )
}

/// CQL depends on the number of shots far more than CQL-MAML.
fn spread_claim(finals: &[Finals]) -> Claim {
    let spread = |pick: fn(&Finals) -> f64| {
        let values = || finals.iter().map(pick);
        values().fold(f64::NEG_INFINITY, f64::max) - values().fold(f64::INFINITY, f64::min)
    };
    let (maml_spread, cql_spread) = (spread(|f| f.maml.mean), spread(|f| f.cql.mean));
    let verdict = if finals.len() < 2 {
        Verdict::Untested
    } else if cql_spread > FAR_MORE * maml_spread {
        Verdict::Yes
    } else if cql_spread > maml_spread {
        Verdict::Partly
    } else {
        Verdict::No
    };
    Claim::new(
        "6",
        "CQL depends on the number of shots far more than CQL-MAML",
        format!(
            "spread of the final return over the sizes: CQL {cql_spread:.0}, CQL-MAML {maml_spread:.0}"
        ),
        verdict,
        || {
            format!(
                "CQL-MAML's final return moves with the shot count by {maml_spread:.0}, CQL's by {cql_spread:.0} \
                 (\"far more\" = at least {FAR_MORE}x)"
            )
        },
    )
}
