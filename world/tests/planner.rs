//! The planner reference against exhaustive enumeration on worlds small enough to enumerate,
//! and against the heuristics on the default world.

use uavmeta_proto::config::{Config, PlannerConfig, RainZone, TaskConfig};
use uavmeta_world::heuristics::{GreedyPolicy, StalestPolicy};
use uavmeta_world::planner::{Planner, PlannerPolicy};
use uavmeta_world::rollout::{evaluate, Policy};
use uavmeta_world::world::World;

fn config(world_toml: &str) -> Config {
    Config::from_toml_str(&format!("[world]\n{world_toml}"), "test", &[]).expect("valid config")
}

/// The cheapest cost -sum r(t) over every action sequence from the world's state to its
/// horizon: a depth-first enumeration of all (5K)^(T - t) sequences, no pruning, no merging.
fn exhaustive(world: &World) -> f64 {
    if world.t() >= world.horizon() {
        return 0.0;
    }
    (0..world.layout().action_count())
        .map(|a| {
            let mut next = world.clone();
            let step = next.step(a);
            -step.reward + exhaustive(&next)
        })
        .fold(f64::INFINITY, f64::min)
}

/// Worlds small enough to enumerate: rain that causes outages, rain that moves, unequal
/// importance weights, the all-devices power term, and an AoI cap that binds.
fn small_worlds() -> Vec<(&'static str, Config, TaskConfig)> {
    let rain = |x0, y0, x1, y1| Some(RainZone { x0, y0, x1, y1 });
    vec![
        (
            "2x2, K=2, T=5, lambda 300",
            config("grid_cells = 2\ndevices = 2\nhorizon = 5\ncell_m = 300.0"),
            TaskConfig::one_off(300.0, None),
        ),
        (
            "3x3, K=2, T=4, rain over one column, lambda 1000",
            config("grid_cells = 3\ndevices = 2\nhorizon = 4\ncell_m = 400.0"),
            TaskConfig::one_off(1000.0, rain(1, 0, 1, 2)),
        ),
        (
            "2x2, K=3, T=4, moving rain, delta per device, aoi_max 3",
            config(
                "grid_cells = 2\ndevices = 3\nhorizon = 4\ncell_m = 500.0\n\
                 delta = [1.0, 2.5, 0.5]\naoi_max = 3",
            ),
            TaskConfig {
                rain_moves_every: Some(2),
                ..TaskConfig::one_off(600.0, rain(0, 0, 0, 0))
            },
        ),
        (
            "2x2, K=2, T=5, all-devices power, lambda 5000",
            config("grid_cells = 2\ndevices = 2\nhorizon = 5\ncell_m = 300.0\npower_term = \"all_devices\""),
            TaskConfig::one_off(5000.0, None),
        ),
    ]
}

/// With a beam wider than the number of distinct states, the search prunes nothing and is
/// exact: from every start cell its plan costs what the best of all sequences costs, and the
/// world charges exactly the cost the plan claims.
#[test]
fn planner_equals_exhaustive_search_on_small_worlds() {
    let wide = Planner::new(&PlannerConfig {
        beam_width: 100_000,
        ..PlannerConfig::default()
    });
    for (name, cfg, task) in small_worlds() {
        let grid = cfg.world.grid_cells;
        for cell in 0..grid * grid {
            let world = World::new(&cfg.world, &task, 3).with_start((cell % grid, cell / grid));
            let best = exhaustive(&world);
            let plan = wide.plan(&world);
            assert_eq!(plan.actions.len(), cfg.world.horizon as usize, "{name}");
            assert!(
                (plan.cost - best).abs() <= 1e-9 * best.abs(),
                "{name}, start cell {cell}: planner {} against exhaustive {best}",
                plan.cost
            );
            // The bound holds on every small world, rain, weights, cap and power term included.
            let bound = world.return_bound();
            assert!(
                -best <= bound + 1e-9 * bound.abs(),
                "{name}, start cell {cell}: the optimum {} above the bound {bound}",
                -best
            );
            let charged = world.cost_of_actions(&plan.actions);
            assert!(
                (charged - plan.cost).abs() <= 1e-9 * charged.abs(),
                "{name}: the plan claims {} but the world charges {charged}",
                plan.cost
            );
        }
    }
}

/// A beam of one is greedy in g + h and prunes: on some small world it misses the optimum, so
/// the exactness above comes from the width, not from the worlds being trivial.
#[test]
fn a_narrow_beam_is_not_exact_on_every_small_world() {
    let narrow = Planner::new(&PlannerConfig {
        beam_width: 1,
        ..PlannerConfig::default()
    });
    let missed = small_worlds().into_iter().any(|(_, cfg, task)| {
        let grid = cfg.world.grid_cells;
        (0..grid * grid).any(|cell| {
            let world = World::new(&cfg.world, &task, 3).with_start((cell % grid, cell / grid));
            narrow.beam(&world).cost > exhaustive(&world) + 1e-6
        })
    });
    assert!(
        missed,
        "a one-state beam matched exhaustive search everywhere"
    );
}

/// On the default world (configs/default.toml's layout) and the unseen lambda = 300, averaged
/// exactly over all 100 start cells, the planner beats both heuristics, and as a policy it plays
/// the plans it makes.
#[test]
fn planner_beats_both_heuristics_on_the_default_world() {
    let path = concat!(env!("CARGO_MANIFEST_DIR"), "/../configs/default.toml");
    let mut cfg = Config::load(path.as_ref(), &[]).expect("configs/default.toml");
    cfg.planner.beam_width = 64;
    let task = cfg.task("lambda-300").expect("lambda-300").clone();
    let planner = evaluate(
        &cfg.world,
        &task,
        &mut PlannerPolicy::new(&cfg.planner),
        1,
        0,
    );
    let stalest = evaluate(&cfg.world, &task, &mut StalestPolicy, 1, 0);
    let greedy = evaluate(&cfg.world, &task, &mut GreedyPolicy, 1, 0);
    assert_eq!(planner.episodes, 100);
    assert!(
        planner.ret.mean > stalest.ret.mean.max(greedy.ret.mean),
        "planner {} against stalest {} and greedy {}",
        planner.ret.mean,
        stalest.ret.mean,
        greedy.ret.mean
    );
    // The bound of docs/MODEL.md section 9: round robin's AoI (5 380 for K = 10, T = 100) with
    // every power from straight above a device (0.031 mW, lambda / K = 30 per mW, 100 steps).
    let bound = World::new(&cfg.world, &task, 0).return_bound();
    assert!(
        (bound + 5380.0 + 0.031 * 30.0 * 100.0).abs() < 1e-6,
        "{bound}"
    );
    assert!(
        planner.ret.mean <= bound,
        "{} above the bound {bound}",
        planner.ret.mean
    );

    let world = World::new(&cfg.world, &task, 0).with_start((4, 7));
    let plan = Planner::new(&cfg.planner).plan(&world);
    let mut policy = PlannerPolicy::new(&cfg.planner);
    let mut w = world.clone();
    let played: Vec<usize> = (0..plan.actions.len())
        .map(|_| {
            let a = policy.act(&w);
            w.step(a);
            a
        })
        .collect();
    assert_eq!(played, plan.actions);
}

/// On a small world where power weighs so much that the best policy leaves the round robin
/// (it serves the nearer devices more often), the default search finds what a search 256 times
/// wider finds, from every start cell: h's discounted power part (`planner.h_power_weights`)
/// does not push it towards the stalest-first order.
#[test]
fn the_default_search_finds_the_wide_searchs_plans_where_serving_out_of_order_pays() {
    let cfg = config("grid_cells = 4\ndevices = 3\nhorizon = 20\ncell_m = 200.0\nlayout_seed = 3");
    let task = TaskConfig::one_off(300.0, None);
    let default = Planner::new(&PlannerConfig::default());
    let wide = Planner::new(&PlannerConfig {
        beam_width: 256 * PlannerConfig::default().beam_width,
        ..PlannerConfig::default()
    });
    let (mut sum_default, mut sum_wide) = (0.0, 0.0);
    for cell in 0..16 {
        let world = World::new(&cfg.world, &task, 0).with_start((cell % 4, cell / 4));
        sum_default += default.beam(&world).cost;
        sum_wide += wide.beam(&world).cost;
    }
    assert!(
        (sum_default - sum_wide).abs() <= 1e-9 * sum_wide,
        "default {sum_default} against wide {sum_wide}"
    );
    // Round robin is not what it finds: the stalest heuristic's AoI is far below the plan's.
    let stalest = evaluate(&cfg.world, &task, &mut StalestPolicy, 1, 0);
    let planned = evaluate(
        &cfg.world,
        &task,
        &mut PlannerPolicy::new(&PlannerConfig::default()),
        1,
        0,
    );
    assert!(
        planned.aoi.mean > stalest.aoi.mean + 0.3,
        "{planned:?} {stalest:?}"
    );
    assert!(planned.ret.mean > stalest.ret.mean);
}

/// The default planner runs one search per weight of `planner.h_power_weights` and keeps the
/// cheapest plan: on lambda-1000 of configs/default.toml's world, from every tenth start cell,
/// its plan costs what the world charges for it, no more than any one weight's plan, and the
/// same as the cheapest of them; and no one weight is the cheapest from every one of those cells.
#[test]
fn the_portfolio_keeps_the_cheapest_of_its_searches() {
    let cfg = config("layout_seed = 7");
    let task = TaskConfig::one_off(1000.0, None);
    let portfolio = Planner::new(&cfg.planner);
    let alone: Vec<Planner> = cfg
        .planner
        .h_power_weights
        .iter()
        .map(|&b| {
            Planner::new(&PlannerConfig {
                h_power_weights: vec![b],
                ..cfg.planner.clone()
            })
        })
        .collect();
    let grid = cfg.world.grid_cells;
    let mut cheapest_weights = std::collections::BTreeSet::new();
    for cell in (0..grid * grid).step_by(10) {
        let world = World::new(&cfg.world, &task, 0).with_start((cell % grid, cell / grid));
        let plan = portfolio.beam(&world);
        assert!((world.cost_of_actions(&plan.actions) - plan.cost).abs() <= 1e-6 * plan.cost.abs());
        let costs: Vec<f64> = alone.iter().map(|p| p.beam(&world).cost).collect();
        let (best, min) =
            costs.iter().enumerate().fold(
                (0, f64::INFINITY),
                |(i, m), (j, &c)| if c < m { (j, c) } else { (i, m) },
            );
        assert_eq!(
            plan.cost, min,
            "cell {cell}: portfolio {} against {costs:?}",
            plan.cost
        );
        cheapest_weights.insert(best);
    }
    assert!(
        cheapest_weights.len() > 1,
        "one weight ({cheapest_weights:?}) was the cheapest from every cell: the portfolio adds nothing here"
    );
}

/// Where power dominates (the default layout at lambda 2000, and at -90 dBm, where every power is
/// 10x), the beam's stalest-first guide misses schedules that serve near devices more often: the
/// local search over its schedule (`uavmeta_world::schedule`) finds cheaper plans from every
/// start cell tried, each one what the world charges, below the bound, never worse than the beam.
#[test]
fn the_schedule_search_improves_the_beam_where_power_dominates() {
    for (world_toml, lambda) in [
        ("layout_seed = 7", 2000.0),
        ("layout_seed = 7\nnoise_dbm = -90.0", 300.0),
    ] {
        let cfg = config(world_toml);
        let task = TaskConfig::one_off(lambda, None);
        let planner = Planner::new(&cfg.planner);
        let (mut beam_sum, mut plan_sum) = (0.0, 0.0);
        for k in 0..8u32 {
            let cell = 7 * k % 100;
            let world = World::new(&cfg.world, &task, 0).with_start((cell % 10, cell / 10));
            let (beam, plan) = (planner.beam(&world), planner.plan(&world));
            let charged = world.cost_of_actions(&plan.actions);
            assert!(
                (charged - plan.cost).abs() <= 1e-9 * charged.abs(),
                "{world_toml}"
            );
            assert!(plan.cost <= beam.cost, "{world_toml}, cell {cell}");
            assert!(
                -plan.cost <= world.return_bound(),
                "{world_toml}, cell {cell}"
            );
            beam_sum += beam.cost;
            plan_sum += plan.cost;
        }
        assert!(
            plan_sum < beam_sum * (1.0 - 1e-3),
            "{world_toml}, lambda {lambda}: the schedule search gained nothing ({plan_sum} against {beam_sum})"
        );
    }
}

/// The schedule search kicks until `patience` kicks in a row find nothing cheaper: its kicks are
/// drawn from the state alone, so more patience replays the same kicks and goes on, and never ends
/// costlier; where power dominates the default's patience (64) gains over none and over 8, and
/// the planner's plan is that search's.
#[test]
fn the_schedule_search_kicks_until_it_stops_gaining() {
    let cfg = config("layout_seed = 7\nnoise_dbm = -90.0");
    let task = TaskConfig::one_off(300.0, None);
    let planner = Planner::new(&cfg.planner);
    let patience = cfg.planner.beam_width / uavmeta_world::schedule::BEAM_PER_KICK;
    let mut sums = [0.0; 3];
    for k in 0..4u32 {
        let cell = 13 * k % 100;
        let world = World::new(&cfg.world, &task, 0).with_start((cell % 10, cell / 10));
        let beam = planner.beam(&world);
        let costs = [0, 8, patience]
            .map(|p| uavmeta_world::schedule::improve(&world, beam.clone(), p).cost);
        assert!(
            costs[0] <= beam.cost && costs[1] <= costs[0] && costs[2] <= costs[1],
            "cell {cell}: patience 0 / 8 / {patience} cost {costs:?}, the beam {}",
            beam.cost
        );
        assert_eq!(planner.plan(&world).cost, costs[2], "cell {cell}");
        for (sum, cost) in sums.iter_mut().zip(costs) {
            *sum += cost;
        }
    }
    assert!(
        sums[2] < sums[1] * (1.0 - 1e-3) && sums[1] < sums[0],
        "patience 0 / 8 / {patience} cost {sums:?} over the cells: the kicks gained nothing"
    );
}

/// A width of 0, and a width and horizon whose search cannot fit the memory bound, are refused
/// naming the key, the value and what was expected.
#[test]
fn planner_keys_are_checked() {
    let bad = |text: &str| {
        Config::from_toml_str(text, "planner.toml", &[])
            .expect_err("refused")
            .to_string()
    };
    let zero = bad("[planner]\nbeam_width = 0\n");
    assert!(
        zero.contains("planner.toml")
            && zero.contains("planner.beam_width")
            && zero.contains("at least 1"),
        "{zero}"
    );
    for weights in ["[]", "[0.25, -1.0]", "[nan]"] {
        let text = bad(&format!("[planner]\nh_power_weights = {weights}\n"));
        assert!(
            text.contains("planner.h_power_weights")
                && text.contains("a non-empty list of finite weights >= 0"),
            "{weights}: {text}"
        );
    }
    let huge = bad("[world]\nhorizon = 100000000\n[planner]\nbeam_width = 100000\n");
    assert!(
        huge.contains("planner.beam_width")
            && huge.contains("100000")
            && huge.contains("planner.max_memory_mib = 1024"),
        "{huge}"
    );
}

/// The planner in the world a run's shots identify (`PlannerPolicy::in_model`): where the shots
/// show every (cell, device) pair the fitted world is the true one, and the plans it makes from
/// the true world's states score what the planner's own do; fitted to shots from one cell, it
/// plans in a pessimistic world and scores no better.
#[test]
fn the_planner_in_the_identified_world_plans_as_the_planner_where_the_shots_fit_every_device() {
    use uavmeta_world::identify::identify;
    use uavmeta_world::rollout::record_step;
    use uavmeta_world::world::Move;
    let config = config("grid_cells = 3\ndevices = 2\nhorizon = 6\ncell_m = 300.0");
    let task = TaskConfig::one_off(2000.0, None);
    let world = World::new(&config.world, &task, 0);
    let (grid, k) = (world.grid_cells(), world.devices());
    let hover = Move::Hover.index() * k;
    let shots_from = |cells: &[(u32, u32)]| {
        let mut shots = Vec::new();
        for &cell in cells {
            for device in 0..k {
                shots.push(record_step(
                    &mut world.clone().with_start(cell),
                    hover + device,
                ));
            }
        }
        shots
    };
    let every: Vec<(u32, u32)> = (0..grid * grid).map(|c| (c % grid, c / grid)).collect();
    let planner = PlannerConfig::default();
    let score = |policy: &mut dyn Policy| evaluate(&config.world, &task, policy, 1, 0).ret.mean;
    let truth = score(&mut PlannerPolicy::new(&planner));
    let fitted = identify(&config.world, &shots_from(&every)).unwrap();
    let modelled = score(&mut PlannerPolicy::in_model(&planner, fitted.world));
    assert!(
        (modelled - truth).abs() < 1e-6 * truth.abs(),
        "{modelled} in the fitted world, {truth} in the true one"
    );
    let partial = identify(&config.world, &shots_from(&[(1, 1)])).unwrap();
    let partial = score(&mut PlannerPolicy::in_model(&planner, partial.world));
    assert!(partial <= truth + 1e-9, "{partial} > {truth}");
}
