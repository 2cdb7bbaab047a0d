//! Figure 9: the rain tasks, resilience to sudden heavy rain.

use super::*;

/// Figure 9 reads the returns off at epochs 100 and 200.
const EPOCH_200: usize = 200;

/// The methods whose final greedy paths on the first rain task figure 9c draws.
pub const PATHS: [Method; 2] = [Method::CQL_MAML, Method::CQL];

/// "About zero" outages per 100-step episode.
const ABOUT_ZERO_OUTAGES: f64 = 1.0;

/// "About 20" outages per episode: within a factor of two.
const ABOUT_20_OUTAGES: (f64, f64) = (10.0, 40.0);

/// One fine-tuning run on a rain task (a task and a seed).
struct RainRun {
    returns: Vec<f64>,
    outages: Vec<f64>,
    /// Its task's random policy: the return above which it can count as converged.
    floor: f64,
}

/// A method's rain runs, task after task, each task's seeds in order.
type MethodRuns = (Method, Vec<RainRun>);

/// A UAV's path: its cells in time order.
type Cells = Vec<(u32, u32)>;

/// Figure 9: the rain tasks.
pub(super) fn resilience(ctx: &Context, dir: &Path) -> Result<Section, ReproduceError> {
    let c = ctx.config;
    let episodes = ctx.reproduce.resilience_eval_episodes;
    let tasks: Vec<&TaskConfig> = rain_tasks(c).collect();
    let online: Vec<PolicyMetrics> = tasks
        .iter()
        .flat_map(|t| ctx.online(&t.name, episodes))
        .collect();
    let heuristics: Vec<&HeuristicRef> = tasks
        .iter()
        .map(|t| ctx.heuristics(&t.name, episodes))
        .collect();
    let refs = Refs::new(c, &online, &heuristics);

    let per_method = rain_runs(ctx, &tasks, &heuristics, dir)?;
    let names: Vec<&str> = tasks.iter().map(|t| t.name.as_str()).collect();
    let planner = ctx.model_planner(&names, ctx.reproduce.main_shots, episodes);
    write_model_planner_csv(ctx, dir, &[&planner])?;
    plot_curves(ctx, tasks.len(), &per_method, &refs, &planner, dir)?;
    let first = tasks[0];
    let (path, in_rain) = trajectories(ctx, first, dir)?;

    let seeds = ctx.seeds.len();
    let summaries: Vec<RainSummary> = per_method
        .iter()
        .map(|(_, runs)| RainSummary::new(runs, seeds))
        .collect();
    let body = summary_table(ctx, &tasks, &per_method, &summaries, &refs, &planner);
    let of = |method: Method| {
        let i = per_method.iter().position(|(m, _)| *m == method);
        i.expect("figure 9 compares CQL-MAML and CQL")
    };
    let (maml, cql) = (of(Method::CQL_MAML), of(Method::CQL));
    // Both claims read the run lengths off CQL-MAML's runs.
    let lens: Vec<usize> = per_method[maml].1.iter().map(|r| r.returns.len()).collect();
    let mut found = vec![
        maml_claim(&summaries[maml], &lens, &refs),
        cql_claim(&summaries[cql], &lens, &refs),
        contrast_claim(&per_method, &summaries, (maml, cql), &refs),
    ];
    if let (&[maml, cql], Some(zone)) = (&in_rain[..], first.rain) {
        found.push(detour_claim(c, first, zone, &path, (maml, cql)));
    }
    finish(body, found)
}

/// Every compared method's runs on every rain task, written to `curves.csv`. The claims compare
/// CQL-MAML and CQL; the others are shown beside them.
fn rain_runs(
    ctx: &Context,
    tasks: &[&TaskConfig],
    heuristics: &[&HeuristicRef],
    dir: &Path,
) -> Result<Vec<MethodRuns>, ReproduceError> {
    let c = ctx.config;
    let mut csv = format!("method,task,{CURVE_COLUMNS}\n");
    let mut per_method = Vec::new();
    for method in compared(c) {
        let mut runs = Vec::new();
        for (task, h) in tasks.iter().zip(heuristics) {
            let key = rain_key(c, ctx.reproduce, task, method);
            let rows = ctx.rows(&key, ctx.reproduce.resilience_epochs);
            curve_lines(
                &mut csv,
                &format!("{},{}", method.name(), task.name),
                ctx.seeds,
                &rows,
            );
            let floor = Refs::new(c, &[], &[h]).random;
            runs.extend(rows.iter().map(|rows| RainRun {
                returns: rows.iter().map(|r| r.policy.ret.mean).collect(),
                outages: rows.iter().map(|r| r.policy.outages.mean).collect(),
                floor,
            }));
        }
        per_method.push((method, runs));
    }
    write_file(&dir.join("curves.csv"), &csv)?;
    Ok(per_method)
}

/// Per seed, the mean over the rain tasks of the curve `pick` takes from each run: a seed's
/// curve in figures 9a and 9b, whose band is over seeds.
fn mean_over_tasks(
    runs: &[RainRun],
    seeds: usize,
    pick: fn(&RainRun) -> &Vec<f64>,
) -> Vec<Vec<f64>> {
    (0..seeds)
        .map(|s| {
            let curves: Vec<&Vec<f64>> = runs.iter().skip(s).step_by(seeds).map(pick).collect();
            let len = curves.iter().map(|c| c.len()).min().unwrap_or(0);
            (0..len)
                .map(|e| curves.iter().map(|c| c[e]).sum::<f64>() / curves.len() as f64)
                .collect()
        })
        .collect()
}

/// Figures 9a (returns) and 9b (outages).
fn plot_curves(
    ctx: &Context,
    tasks: usize,
    per_method: &[MethodRuns],
    refs: &Refs,
    planner: &ModelPlanner,
    dir: &Path,
) -> Result<(), ReproduceError> {
    let seeds = ctx.seeds.len();
    let returns: Vec<Series> = per_method
        .iter()
        .map(|(m, runs)| {
            return_series(
                chart_label(*m),
                &mean_over_tasks(runs, seeds, |r| &r.returns),
            )
        })
        .collect();
    let lines: Vec<Reference> = refs.lines().into_iter().chain(planner.line()).collect();
    line_chart(
        &dir.join("fig9a_return.png"),
        &format!("Figure 9a: {tasks} rain tasks, mean over tasks"),
        &returns,
        &lines,
    )?;
    let outages: Vec<Series> = per_method
        .iter()
        .map(|(m, runs)| {
            series(
                chart_label(*m),
                &mean_over_tasks(runs, seeds, |r| &r.outages),
            )
        })
        .collect();
    let chart = LineChart {
        title: &format!(
            "Figure 9b: outages per episode ({} episodes per point)",
            tasks * seeds * ctx.reproduce.resilience_eval_episodes
        ),
        x_label: "epoch",
        y_label: "outages per episode",
        series: &outages,
        references: &[Reference {
            label: "online DQN".into(),
            value: refs.online_outages.mean,
        }],
        floor: Some(0.0),
    };
    Ok(plot::line_chart(&dir.join("fig9b_outages.png"), &chart)?)
}

/// Figure 9c: the first seed's final greedy paths on the first rain task, CQL-MAML's then CQL's.
/// Returns CQL-MAML's path and each method's steps inside the zone.
fn trajectories(
    ctx: &Context,
    first: &TaskConfig,
    dir: &Path,
) -> Result<(Cells, Vec<u32>), ReproduceError> {
    let c = ctx.config;
    let mut csv = String::from("method,t,x,y\n");
    let mut paths = Vec::new();
    let mut in_rain = Vec::new();
    if let Some(seed) = ctx.seeds.first() {
        for method in PATHS {
            let trajectory = seed
                .run(&rain_key(c, ctx.reproduce, first, method))
                .trajectory
                .as_ref()
                .expect("the plan records the first rain task's paths");
            for (t, (x, y)) in trajectory.cells.iter().enumerate() {
                let _ = writeln!(csv, "{},{t},{x},{y}", method.name());
            }
            paths.push((method.label().to_string(), trajectory.cells.clone()));
            in_rain.push(trajectory.metrics.outages);
        }
    }
    write_file(&dir.join("fig9c_trajectories.csv"), &csv)?;
    let world = World::new(&c.world, first, 0);
    plot::trajectory_chart(
        &dir.join("fig9c_trajectories.png"),
        &TrajectoryChart {
            title: &format!("Figure 9c: `{}`, final greedy paths (seed 0)", first.name),
            grid_cells: c.world.grid_cells,
            device_cells: world.device_cells(),
            rain: first.rain,
            paths: &paths,
        },
    )?;
    let maml_path = paths.into_iter().next().map(|(_, cells)| cells);
    Ok((maml_path.unwrap_or_default(), in_rain))
}

/// A method's figures over the rain runs.
struct RainSummary {
    /// Per run, the epoch it converged at.
    converged: Vec<Option<usize>>,
    /// Over seeds, each seed's final return and outages (means over the tasks).
    finals: Estimate,
    outages: Estimate,
}

impl RainSummary {
    fn new(runs: &[RainRun], seeds: usize) -> Self {
        let last = |pick: fn(&RainRun) -> &Vec<f64>| {
            est(mean_over_tasks(runs, seeds, pick)
                .iter()
                .map(|c| final_return(c)))
        };
        RainSummary {
            converged: runs
                .iter()
                .map(|r| converged_at(&r.returns, r.floor))
                .collect(),
            finals: last(|r| &r.returns),
            outages: last(|r| &r.outages),
        }
    }

    /// "n/m": of the m runs, n converged.
    fn converged_share(&self) -> String {
        let n = self.converged.iter().flatten().count();
        format!("{n}/{}", self.converged.len())
    }
}

/// The summary's opening and its table of methods.
fn summary_table(
    ctx: &Context,
    tasks: &[&TaskConfig],
    per_method: &[MethodRuns],
    summaries: &[RainSummary],
    refs: &Refs,
    planner: &ModelPlanner,
) -> String {
    let r = ctx.reproduce;
    let (epochs, episodes) = (r.resilience_epochs, r.resilience_eval_episodes);
    let seeds = ctx.seeds.len();
    let total = tasks.len() * seeds * episodes;
    let mut body = format!(
        "{} rain tasks ({}), every compared method (its init trained on the first {} rain-free \
         tasks, or random), fine-tuned for {epochs} epochs on {} shots of each, {}; every evaluation runs \
         {episodes} episodes, so each point of figure 9b averages {} tasks x {seeds} seeds x {episodes} = \
         {total} Monte-Carlo episodes. Convergence as in figure 5, against each task's random policy.\n\n\
         | method | converged (task x seed runs) | final return (vs the tasks' mean planner) | final outages per episode |\n| --- | --- | --- | --- |\n",
        tasks.len(),
        joined(tasks.iter().map(|t| &t.name), ", "),
        r.meta_tasks,
        r.main_shots,
        ctx.seeds_note(),
        tasks.len(),
    );
    let rows = per_method.iter().zip(summaries);
    let (model_free, model_based): (Vec<_>, Vec<_>) =
        rows.partition(|((m, _), _)| !m.model_based());
    let line = |body: &mut String, ((method, _), s): (&MethodRuns, &RainSummary)| {
        let _ = writeln!(
            body,
            "| {} | {} | {} | {:.1} |",
            method.label(),
            s.converged_share(),
            refs.with_gap(s.finals),
            s.outages
        );
    };
    model_free.into_iter().for_each(|row| line(&mut body, row));
    let planned = planner.ret().zip(planner.estimate(3));
    if !model_based.is_empty() || planned.is_some() {
        body.push_str(&model_based_row(3));
    }
    model_based.into_iter().for_each(|row| line(&mut body, row));
    if let Some((ret, outages)) = planned {
        let _ = writeln!(
            body,
            "| {MODEL_PLANNER} | | {} | {outages:.1} |",
            refs.with_gap(ret)
        );
    }
    let _ = writeln!(
        body,
        "| *references* | | | |\n| online DQN | | {} | {:.1} |",
        refs.with_gap(refs.online),
        refs.online_outages
    );
    body.push_str(&planner.note());
    body
}

/// Figure 9's claim for CQL-MAML: it converges within 100 epochs with about zero outages.
fn maml_claim(maml: &RainSummary, lens: &[usize], refs: &Refs) -> Claim {
    let cases = maml.converged.iter().zip(lens).map(|(c, &len)| match c {
        Some(e) if *e <= EPOCH_100 => Verdict::Yes,
        None if len < EPOCH_100 => Verdict::Untested,
        _ => Verdict::No,
    });
    let converged = Verdict::all_of(cases);
    let (outages, finals) = (maml.outages, maml.finals);
    let quiet = Verdict::within(outages, f64::NEG_INFINITY, ABOUT_ZERO_OUTAGES);
    Claim::new(
        "9",
        "On 5 unseen rain tasks CQL-MAML converges within 100 epochs and reaches about zero outages",
        format!(
            "converged in {} runs; final outages {outages:.1} per episode; final return {finals:.0}",
            maml.converged_share()
        ),
        Verdict::all_of([converged, quiet]),
        || {
            let mut why = vec![];
            if converged != Verdict::Yes {
                why.push(refs.shortfall(&[("CQL-MAML", finals.mean)]));
            }
            if quiet != Verdict::Yes {
                why.push(format!(
                    "its greedy policy still flies through rain ({outages:.1} outages per episode; online DQN {:.1}): \
                     the zone is not in the observation and the shots rarely show its cost",
                    refs.online_outages
                ));
            }
            why.retain(|w| !w.is_empty());
            why.join("; ")
        },
    )
}

/// Figure 9's claim for CQL: it does not converge in 200 epochs and has about 20 outages.
fn cql_claim(cql: &RainSummary, lens: &[usize], refs: &Refs) -> Claim {
    let cases = cql.converged.iter().zip(lens).map(|(c, &len)| match c {
        Some(e) if *e <= EPOCH_200 => Verdict::No,
        None if len < EPOCH_200 => Verdict::Untested,
        _ => Verdict::Yes,
    });
    let stuck = Verdict::all_of(cases);
    let (outages, finals) = (cql.outages, cql.finals);
    let about_20 = Verdict::within(outages, ABOUT_20_OUTAGES.0, ABOUT_20_OUTAGES.1);
    Claim::new(
        "9",
        "CQL does not converge in 200 epochs and has about 20 outages per episode",
        format!(
            "converged in {} runs; final outages {outages:.1} per episode; final return {finals:.0}",
            cql.converged_share()
        ),
        Verdict::all_of([stuck, about_20]),
        || {
            let mut why = vec![];
            if stuck == Verdict::No || stuck == Verdict::Partly {
                why.push("CQL settles at a useful return in some runs".to_string());
            }
            if about_20 != Verdict::Yes {
                why.push(format!(
                    "{outages:.1} outages per episode, not wholly within {}-{}; the online DQN agent has {:.1} on the same \
                     zones, so how often a policy crosses them is set by where they lie on its routes",
                    ABOUT_20_OUTAGES.0, ABOUT_20_OUTAGES.1, refs.online_outages
                ));
            }
            why.join("; ")
        },
    )
}

/// Figure 9's contrast: CQL-MAML ends above CQL on the rain tasks, in return and in outages, each
/// judged on the seeds' intervals (`Verdict::beats`), beside the planner and the strongest other
/// method.
fn contrast_claim(
    per_method: &[MethodRuns],
    summaries: &[RainSummary],
    (maml, cql): (usize, usize),
    refs: &Refs,
) -> Claim {
    let (m, c) = (&summaries[maml], &summaries[cql]);
    let fewer = |a: Estimate| Estimate {
        mean: -a.mean,
        ci95: a.ci95,
    };
    let ret = Verdict::beats(m.finals, c.finals);
    let quiet = Verdict::beats(fewer(m.outages), fewer(c.outages));
    let strongest = per_method
        .iter()
        .zip(summaries)
        .enumerate()
        .filter(|(i, ((method, _), _))| *i != maml && !method.model_based())
        .max_by(|(_, (_, a)), (_, (_, b))| a.finals.mean.total_cmp(&b.finals.mean))
        .map(|(_, ((method, _), s))| (method.label(), s));
    let strongest = strongest.map_or(String::new(), |(label, s)| {
        format!(
            "; the strongest other method, {label}: {} with {:.1}",
            refs.with_gap(s.finals),
            s.outages
        )
    });
    let planner = refs
        .planner
        .map_or(String::new(), |p| format!("; planner {p:.0}"));
    Claim::new(
        "9",
        "CQL-MAML adapts to rain better than CQL: a higher return and fewer outages",
        format!(
            "return CQL-MAML {} against CQL {}; outages per episode {:.1} against {:.1}{planner}{strongest}",
            refs.with_gap(m.finals),
            refs.with_gap(c.finals),
            m.outages,
            c.outages
        ),
        Verdict::all_of([ret, quiet]),
        || {
            let part = |verdict, overlap: &str, worse: &str| match verdict {
                Verdict::Partly => Some(overlap.to_string()),
                Verdict::No => Some(worse.to_string()),
                _ => None,
            };
            [
                part(ret, "the seeds' return intervals overlap", "CQL's return is as high or higher"),
                part(quiet, "the seeds' outage intervals overlap", "CQL has as few outages or fewer"),
            ]
            .into_iter()
            .flatten()
            .collect::<Vec<_>>()
            .join("; ")
        },
    )
}

/// Figure 9c's claim: CQL-MAML's `path` flies around `zone`, from the steps CQL-MAML and CQL
/// spent inside it.
fn detour_claim(
    c: &Config,
    first: &TaskConfig,
    zone: RainZone,
    path: &[(u32, u32)],
    (maml, cql): (u32, u32),
) -> Claim {
    // Flying around the zone means coming up to it without entering: a path that never gets
    // near it shows a policy that does not go there, not one that avoids it.
    let closest = path
        .iter()
        .map(|&(x, y)| cells_from(zone, x, y))
        .min()
        .unwrap_or(u32::MAX);
    Claim::new(
        "9",
        "The trajectory plot shows CQL-MAML flying around the rain zone",
        format!(
            "on `{}` (seed 0), steps inside the zone: CQL-MAML {maml}, CQL {cql}; CQL-MAML's closest cell is \
             {closest} cell(s) from it",
            first.name
        ),
        if maml == 0 && closest <= 1 {
            Verdict::Yes
        } else if maml < cql {
            Verdict::Partly
        } else {
            Verdict::No
        },
        || {
            if maml == 0 {
                format!(
                    "CQL-MAML never comes within a cell of the zone ({closest} away), so the path shows no \
                     detour, only a policy that does not fly there"
                )
            } else if maml < cql {
                format!("CQL-MAML enters the zone less often than CQL but still for {maml} steps")
            } else {
                format!(
                    "CQL-MAML's path crosses the zone for {maml} of {} steps",
                    c.world.horizon
                )
            }
        },
    )
}

/// Cells between (x, y) and `zone` in king moves (0 inside, 1 on its border ring).
fn cells_from(zone: RainZone, x: u32, y: u32) -> u32 {
    let gap = |v: u32, lo: u32, hi: u32| lo.saturating_sub(v).max(v.saturating_sub(hi));
    gap(x, zone.x0, zone.x1).max(gap(y, zone.y0, zone.y1))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cells_from_a_zone_count_king_moves() {
        let zone = RainZone {
            x0: 4,
            y0: 2,
            x1: 6,
            y1: 4,
        };
        assert_eq!(cells_from(zone, 5, 3), 0);
        assert_eq!(cells_from(zone, 3, 1), 1);
        assert_eq!(cells_from(zone, 7, 4), 1);
        assert_eq!(cells_from(zone, 9, 8), 4);
        assert_eq!(cells_from(zone, 0, 3), 4);
    }
}
