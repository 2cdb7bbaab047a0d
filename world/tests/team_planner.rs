//! The team's planner reference (docs/MODEL.md section 11) against exact dynamic programming over
//! every joint action on worlds small enough to enumerate, its bound, and the team heuristics.

use std::collections::HashMap;

use uavmeta_proto::config::{Config, PlannerConfig, RainZone, RiskyRegion, TaskConfig};
use uavmeta_world::heuristics::{GreedyPolicy, StalestPolicy};
use uavmeta_world::planner::{Planner, PlannerPolicy};
use uavmeta_world::rollout::{run_episode, Policy};
use uavmeta_world::world::World;

fn config(world_toml: &str) -> Config {
    Config::from_toml_str(&format!("[world]\n{world_toml}"), "team.toml", &[])
        .expect("test config is valid")
}

/// The least cost -sum r(t) over every joint action sequence from the world's state to its
/// horizon: every joint action at every step, memoised on the whole state (the worlds here are
/// deterministic, so the state and t decide the rest).
fn optimum(world: &World, memo: &mut HashMap<(Vec<u16>, u32), f64>) -> f64 {
    if world.t() >= world.horizon() {
        return 0.0;
    }
    let key = (world.observation().to_vec(), world.t());
    if let Some(&cost) = memo.get(&key) {
        return cost;
    }
    let (uavs, count) = (world.uavs(), world.layout().action_count());
    let mut best = f64::INFINITY;
    for joint in 0..count.pow(uavs as u32) {
        let actions: Vec<usize> = (0..uavs)
            .map(|u| joint / count.pow(u as u32) % count)
            .collect();
        let mut next = world.clone();
        let step = next.step_team(&actions);
        best = best.min(-step.reward + optimum(&next, memo));
    }
    memo.insert(key, best);
    best
}

/// What the world charges for `actions` (U a step) from its state, on a copy.
fn charged(world: &World, actions: &[usize]) -> f64 {
    let mut w = world.clone();
    actions
        .chunks(w.uavs())
        .map(|step| -w.step_team(step).reward)
        .sum()
}

/// Teams small enough to enumerate: two UAVs sharing devices, "none" among the targets, moves of
/// two cells, rain that puts one UAV in outage, a risky region charged at its expectation.
fn small_teams() -> Vec<(&'static str, Config, TaskConfig)> {
    let rain = Some(RainZone {
        x0: 0,
        y0: 0,
        x1: 0,
        y1: 2,
    });
    let risky = RiskyRegion {
        x0: 1,
        y0: 1,
        x1: 2,
        y1: 2,
        penalty: 40.0,
        probability: 0.5,
    };
    vec![
        (
            "2 UAVs, 2x2, K=2, T=4, lambda 300",
            config("grid_cells = 2\ndevices = 2\nhorizon = 4\ncell_m = 300.0\nuavs = 2"),
            TaskConfig::one_off(300.0, None),
        ),
        (
            "2 UAVs, 3x3, K=3, T=3, idle, steps of 2, rain over a column, lambda 2000",
            config(
                "grid_cells = 3\ndevices = 3\nhorizon = 3\ncell_m = 400.0\nuavs = 2\n\
                 idle_action = true\nstep_cells = 2",
            ),
            TaskConfig::one_off(2000.0, rain),
        ),
        (
            "2 UAVs, 3x3, K=2, T=3, idle, a risky block, weights per device, lambda 600",
            config(
                "grid_cells = 3\ndevices = 2\nhorizon = 3\ncell_m = 500.0\nuavs = 2\n\
                 idle_action = true\ndelta = [2.0, 0.5]",
            ),
            TaskConfig {
                risky: Some(risky),
                ..TaskConfig::one_off(600.0, None)
            },
        ),
    ]
}

/// With a beam wider than the distinct joint states, the team's search prunes nothing: from
/// every joint start its plan costs the optimum, the world charges what the plan claims, and the
/// bound is at or above the optimum's return.
#[test]
fn the_team_planner_is_exact_when_its_beam_holds_every_state() {
    let wide = Planner::new(&PlannerConfig {
        beam_width: 100_000,
        ..PlannerConfig::default()
    });
    for (name, cfg, task) in small_teams() {
        let grid = cfg.world.grid_cells;
        let cells: Vec<(u32, u32)> = (0..grid * grid).map(|c| (c % grid, c / grid)).collect();
        for &a in &cells {
            for &b in &cells {
                let world = World::new(&cfg.world, &task, 3)
                    .expecting_risk()
                    .with_starts(&[a, b]);
                let best = optimum(&world, &mut HashMap::new());
                let plan = wide.plan(&world);
                assert_eq!(plan.actions.len(), 2 * cfg.world.horizon as usize, "{name}");
                let at = format!("{name}, starts {a:?} {b:?}");
                assert!(
                    (plan.cost - best).abs() <= 1e-9 * best.abs(),
                    "{at}: planner {} against the optimum {best}",
                    plan.cost
                );
                let cost = charged(&world, &plan.actions);
                assert!(
                    (cost - plan.cost).abs() <= 1e-9 * cost.abs(),
                    "{at}: the plan claims {} but the world charges {cost}",
                    plan.cost
                );
                let bound = world.return_bound();
                assert!(
                    -best <= bound + 1e-9 * bound.abs(),
                    "{at}: the optimum's return {} above the bound {bound}",
                    -best
                );
            }
        }
    }
}

/// A beam of one prunes: on some small team it misses the optimum, so the exactness above comes
/// from the width.
#[test]
fn a_one_state_team_beam_is_not_exact_everywhere() {
    let narrow = Planner::new(&PlannerConfig {
        beam_width: 1,
        ..PlannerConfig::default()
    });
    let missed = small_teams().into_iter().any(|(_, cfg, task)| {
        let grid = cfg.world.grid_cells;
        (0..grid * grid).any(|c| {
            let start = (c % grid, c / grid);
            let world = World::new(&cfg.world, &task, 3)
                .expecting_risk()
                .with_starts(&[start, (0, 0)]);
            narrow.beam(&world).cost > optimum(&world, &mut HashMap::new()) + 1e-6
        })
    });
    assert!(missed, "a one-state beam matched the optimum everywhere");
}

/// The authors' setting in small (two UAVs, ten devices, moves of two cells, "none" among the
/// targets): over a fixed set of joint starts the planner, as a policy, beats both team
/// heuristics, and stays below the bound.
#[test]
fn the_team_planner_beats_the_team_heuristics() {
    let cfg = config("devices = 10\nuavs = 2\nstep_cells = 2\nidle_action = true");
    let task = TaskConfig::one_off(300.0, None);
    let planner = PlannerConfig {
        beam_width: 16,
        h_power_weights: vec![0.5],
        ..PlannerConfig::default()
    };
    let starts = [[(0, 0), (9, 9)], [(4, 5), (4, 5)], [(2, 7), (8, 1)]];
    let score = |policy: &mut dyn Policy| -> f64 {
        let mut total = 0.0;
        for cells in &starts {
            let mut world = World::new(&cfg.world, &task, 5).with_starts(cells);
            total += run_episode(&mut world, policy).ret;
        }
        total / starts.len() as f64
    };
    let planned = score(&mut PlannerPolicy::new(&planner));
    let greedy = score(&mut GreedyPolicy);
    let stalest = score(&mut StalestPolicy);
    assert!(
        planned > greedy && planned > stalest,
        "planner {planned} against greedy {greedy} and stalest {stalest}"
    );
    let bound = World::new(&cfg.world, &task, 5).return_bound();
    assert!(
        planned <= bound,
        "planner {planned} above the bound {bound}"
    );
}

/// A team whose search would not fit `planner.max_memory_mib` still loads (its heuristics fly
/// it), and asking it for the planner is refused with the memory it would need.
#[test]
fn a_team_too_large_to_search_is_refused_where_the_planner_is_asked_for() {
    let three = config("devices = 10\nuavs = 3");
    let error = uavmeta_world::heuristics::PolicySpec::Planner
        .build(&three, 0, None)
        .err()
        .expect("a search of 125 000 children a node is refused");
    let text = error.to_string();
    assert!(
        text.contains("planner.max_memory_mib") && text.contains("world.uavs = 3"),
        "{text}"
    );
    let two = config("devices = 10\nuavs = 2");
    assert!(uavmeta_world::heuristics::PolicySpec::Planner
        .build(&two, 0, None)
        .is_ok());
}
