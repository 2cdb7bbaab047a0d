//! Figure 5: the four methods on the unseen task.

use super::*;

/// How many runs converged, and at which epoch (see [`claims::converged_at`]).
fn convergence_cells(runs: &[Vec<f64>], floor: f64) -> String {
    let epochs: Vec<usize> = runs.iter().filter_map(|r| converged_at(r, floor)).collect();
    match epochs.len() {
        0 => format!("0/{}", runs.len()),
        n => format!(
            "{n}/{} (epoch {:.1})",
            runs.len(),
            est(epochs.iter().map(|&e| e as f64))
        ),
    }
}

/// Figure 5: the four methods on the unseen task.
pub(super) fn convergence(ctx: &Context, dir: &Path) -> Result<Section, ReproduceError> {
    let c = ctx.config;
    let r = ctx.reproduce;
    let refs = ctx.unseen_refs();
    let mut csv = format!("method,{CURVE_COLUMNS}\n");
    let runs: Vec<(Method, Vec<Vec<f64>>)> = fine_tuned(c)
        .into_iter()
        .map(|method| {
            let key = unseen_key(c, r, method, r.main_shots, r.meta_tasks);
            let curves = ctx.curves(&mut csv, &method.name(), &key, r.convergence_epochs);
            (method, curves)
        })
        .collect();
    write_file(&dir.join("curves.csv"), &csv)?;
    write_references_csv(ctx, dir, &r.unseen_task, c.learner.eval_episodes)?;
    let planner = ctx.model_planner(&[&r.unseen_task], r.main_shots, c.learner.eval_episodes);
    write_model_planner_csv(ctx, dir, &[&planner])?;
    let series: Vec<Series> = runs
        .iter()
        .map(|(m, runs)| return_series(chart_label(*m), runs))
        .collect();
    let lines: Vec<Reference> = refs.lines().into_iter().chain(planner.line()).collect();
    line_chart(
        &dir.join("fig5.png"),
        &format!(
            "Figure 5: fine-tuning on `{}` ({} shots)",
            r.unseen_task, r.main_shots
        ),
        &series,
        &lines,
    )?;

    let body = summary_table(ctx, &runs, &refs, &planner);
    let runs_of = |m: Method| of_method(&runs, m);
    let (maml, cql) = (runs_of(Method::CQL_MAML), runs_of(Method::CQL));
    let mut found = vec![
        dqn_claim(runs_of(Method::DQN), runs_of(Method::DQN_MAML), &refs),
        cql_claim(cql, &refs, r.convergence_epochs),
        maml_claim(maml, &refs),
        online_claim(maml, cql, &refs),
    ];
    let online = ctx.online(&r.unseen_task, c.learner.eval_episodes);
    found.extend(seed_claims(maml, cql, &online, &refs));
    finish(body, found)
}

/// Over seeds: the return at epoch 40, the final return and the mean swing between epochs.
fn curve_stats(runs: &[Vec<f64>]) -> (Estimate, Estimate, Estimate) {
    (
        est(runs.iter().map(|r| return_at(r, EPOCH_40))),
        finals(runs),
        est(runs.iter().map(|r| mean_swing(r))),
    )
}

/// The summary's opening, its table of methods (the model-based ones and the planner in the
/// fitted world in a section of their own) and the reference levels.
fn summary_table(
    ctx: &Context,
    runs: &[(Method, Vec<Vec<f64>>)],
    refs: &Refs,
    planner: &ModelPlanner,
) -> String {
    let c = ctx.config;
    let r = ctx.reproduce;
    let mut body = format!(
        "Fine-tuning on {} shots of the unseen task `{}` for {} epochs, {}. A run *converged* \
         when its {}-epoch moving average stays within 5% of its final return (the mean of its last {} \
         epochs) before the last {:.0}% of its epochs, at a final return above the uniform random \
         policy's ({:.0}).\n\n",
        r.main_shots,
        r.unseen_task,
        r.convergence_epochs,
        ctx.seeds_note(),
        claims::SMOOTH_EPOCHS,
        claims::FINAL_EPOCHS,
        claims::LATE_SHARE * 100.0,
        refs.random
    );
    let _ = writeln!(
        body,
        "| method | converged (seeds) | return at epoch {EPOCH_40} | final return (vs planner) | mean swing between epochs |\n| --- | --- | --- | --- | --- |"
    );
    let (model_free, model_based): (Vec<_>, Vec<_>) =
        runs.iter().partition(|(m, _)| !m.model_based());
    let line = |body: &mut String, (method, runs): &(Method, Vec<Vec<f64>>)| {
        let (at40, last, swing) = curve_stats(runs);
        let converged = convergence_cells(runs, refs.random);
        let _ = writeln!(
            body,
            "| {} | {converged} | {at40:.0} | {} | {swing:.0} |",
            method.label(),
            refs.with_gap(last)
        );
    };
    model_free.into_iter().for_each(|run| line(&mut body, run));
    let planned = planner.ret();
    if !model_based.is_empty() || planned.is_some() {
        body.push_str(&model_based_row(4));
    }
    model_based.into_iter().for_each(|run| line(&mut body, run));
    if let Some(ret) = planned {
        let _ = writeln!(
            body,
            "| {MODEL_PLANNER} | - | - | {} | - |",
            refs.with_gap(ret)
        );
    }
    body.push_str(&planner.note());
    body.push('\n');
    body.push_str(&references_table(
        ctx,
        &r.unseen_task,
        c.learner.eval_episodes,
    ));
    body
}

/// DQN and DQN-MAML fail to converge.
fn dqn_claim(dqn: &[Vec<f64>], dqn_maml: &[Vec<f64>], refs: &Refs) -> Claim {
    let all: Vec<&Vec<f64>> = dqn.iter().chain(dqn_maml).collect();
    let failed = all
        .iter()
        .filter(|r| converged_at(r, refs.random).is_none())
        .count();
    let measured = [(Method::DQN, dqn), (Method::DQN_MAML, dqn_maml)].map(|(m, runs)| {
        let cell = convergence_cells(runs, refs.random);
        format!(
            "{} converged in {cell}, final {:.0}",
            m.label(),
            finals(runs)
        )
    });
    Claim::new(
        "5",
        "DQN and DQN-MAML trained offline fail to converge",
        measured.join("; "),
        Verdict::share(failed, all.len()),
        || {
            format!(
                "{} of {} DQN / DQN-MAML runs settled above the random policy's return",
                all.len() - failed,
                all.len()
            )
        },
    )
}

/// CQL needs more than 100 epochs: a run that converged by epoch 100 refutes it; one that did
/// not within fewer than 100 epochs leaves it open.
fn cql_claim(cql: &[Vec<f64>], refs: &Refs, epochs: usize) -> Claim {
    let cases = cql.iter().map(|r| match converged_at(r, refs.random) {
        Some(e) if e <= EPOCH_100 => Verdict::No,
        None if r.len() < EPOCH_100 => Verdict::Untested,
        _ => Verdict::Yes,
    });
    let cell = convergence_cells(cql, refs.random);
    Claim::new(
        "5",
        "CQL from a random init needs more than 100 epochs",
        format!(
            "CQL converged in {cell}; final {:.0} (random policy {:.0})",
            finals(cql),
            refs.random
        ),
        Verdict::all_of(cases),
        || {
            format!(
                "CQL settled at a useful return within {} epochs in some seeds",
                epochs.min(EPOCH_100)
            )
        },
    )
}

/// CQL-MAML converges in fewer than 40 epochs.
fn maml_claim(maml: &[Vec<f64>], refs: &Refs) -> Claim {
    let cases = maml.iter().map(|r| match converged_at(r, refs.random) {
        Some(e) if e < EPOCH_40 => Verdict::Yes,
        None if r.len() < EPOCH_40 => Verdict::Untested,
        _ => Verdict::No,
    });
    let cell = convergence_cells(maml, refs.random);
    let (_, maml_final, maml_swing) = curve_stats(maml);
    Claim::new(
        "5",
        "CQL-MAML converges in fewer than 40 epochs",
        format!("CQL-MAML converged in {cell}; final {maml_final:.0}"),
        Verdict::all_of(cases),
        || {
            let short = refs.shortfall(&[("CQL-MAML", maml_final.mean)]);
            if short.is_empty() {
                format!(
                    "its returns swing by {maml_swing:.0} between epochs, wider than the 5% band ({:.0}) around its final return",
                    0.05 * maml_final.mean.abs()
                )
            } else {
                short
            }
        },
    )
}

/// CQL-MAML and CQL both end above the online DQN agent.
fn online_claim(maml: &[Vec<f64>], cql: &[Vec<f64>], refs: &Refs) -> Claim {
    let (maml_final, cql_final) = (finals(maml), finals(cql));
    let verdicts = [
        Verdict::beats(maml_final, refs.online),
        Verdict::beats(cql_final, refs.online),
    ];
    Claim::new(
        "5",
        "CQL-MAML and CQL both end above the online DQN agent",
        format!(
            "final: CQL-MAML {maml_final:.0}, CQL {cql_final:.0}; online DQN {:.0}",
            refs.online
        ),
        Verdict::all_of(verdicts),
        || refs.shortfall(&[("CQL-MAML", maml_final.mean), ("CQL", cql_final.mean)]),
    )
}

/// The same two statements seed by seed, each seed against its own online agent and its own
/// CQL run: at epoch 40 CQL-MAML is at or above the agent, and it settles within 5% of its
/// final return in at most half the epochs CQL takes.
fn seed_claims(
    maml: &[Vec<f64>],
    cql: &[Vec<f64>],
    online: &[PolicyMetrics],
    refs: &Refs,
) -> [Claim; 2] {
    let at_40: Vec<bool> = maml
        .iter()
        .zip(online)
        .filter(|(run, _)| run.len() >= EPOCH_40)
        .map(|(run, agent)| return_at(run, EPOCH_40) >= agent.ret.mean)
        .collect();
    let held = at_40.iter().filter(|&&above| above).count();
    let above = Claim::new(
        "5",
        "At epoch 40 CQL-MAML is at or above the online DQN agent (on at least 4 of 5 seeds)",
        format!("{held} of {} seeds", at_40.len()),
        match at_40.len() {
            0 => Verdict::Untested,
            n if 5 * held >= 4 * n => Verdict::Yes,
            n => Verdict::share(held, n),
        },
        || {
            format!(
                "CQL-MAML at epoch 40: {:.0}; online DQN {:.0}",
                est(maml.iter().map(|run| return_at(run, EPOCH_40))),
                refs.online
            )
        },
    );
    let settles: Vec<(usize, usize)> = maml
        .iter()
        .zip(cql)
        .map(|(m, c)| (settle_epoch(m), settle_epoch(c)))
        .collect();
    let faster = settles.iter().filter(|(m, c)| 2 * m <= *c).count();
    let settled = Claim::new(
        "5",
        "CQL-MAML reaches 95% of its final return in at most half the epochs CQL needs",
        format!(
            "{faster} of {} seeds; settle epochs CQL-MAML / CQL: {}",
            settles.len(),
            joined(settles.iter().map(|(m, c)| format!("{m}/{c}")), ", ")
        ),
        Verdict::share(faster, settles.len()),
        || "in some seeds CQL settles as early as CQL-MAML, or CQL-MAML keeps moving".into(),
    );
    [above, settled]
}

fn write_references_csv(
    ctx: &Context,
    dir: &Path,
    task: &str,
    episodes: usize,
) -> Result<(), ReproduceError> {
    let mut csv = String::from("reference,task,seed,return,aoi,power_mw,outages\n");
    for (seed, m) in ctx.seeds.iter().zip(ctx.online(task, episodes)) {
        let _ = writeln!(
            csv,
            "online-dqn,{task},{},{},{},{},{}",
            seed.seed, m.ret.mean, m.aoi.mean, m.power_mw.mean, m.outages.mean
        );
    }
    for (name, m) in &ctx.heuristics(task, episodes).policies {
        let _ = writeln!(
            csv,
            "{name},{task},,{},{},{},{}",
            m.ret.mean, m.aoi.mean, m.power_mw.mean, m.outages.mean
        );
    }
    Ok(write_file(&dir.join("references.csv"), &csv)?)
}

fn references_table(ctx: &Context, task: &str, episodes: usize) -> String {
    let online = ctx.online(task, episodes);
    let mut s = format!(
        "| reference on `{task}` | return | AoI | power (mW) | outages |\n| --- | --- | --- | --- | --- |\n"
    );
    let _ = writeln!(
        s,
        "| online DQN (over seeds) | {:.0} | {:.2} | {:.3} | {:.1} |",
        est(online.iter().map(|m| m.ret.mean)),
        est(online.iter().map(|m| m.aoi.mean)),
        est(online.iter().map(|m| m.power_mw.mean)),
        est(online.iter().map(|m| m.outages.mean)),
    );
    for (name, m) in &ctx.heuristics(task, episodes).policies {
        let _ = writeln!(
            s,
            "| {name} (over {} episodes) | {:.0} | {:.2} | {:.3} | {:.1} |",
            m.episodes, m.ret, m.aoi, m.power_mw, m.outages
        );
    }
    s
}
