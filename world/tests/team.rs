//! A team of UAVs (docs/MODEL.md section 11) against hand-computed steps: two UAVs on one device,
//! the idle target, moves of several cells, rain per UAV, the risky region drawn and expected,
//! exact evaluation over joint start cells, and the heuristics' claims.

use std::collections::HashSet;

use uavmeta_proto::config::{Config, RainZone, RiskyRegion, TaskConfig, MAX_JOINT_STARTS};
use uavmeta_proto::dataset::Transition;
use uavmeta_proto::stats::PolicyMetrics;
use uavmeta_world::heuristics::{GreedyPolicy, PolicySpec, RandomPolicy, StalestPolicy};
use uavmeta_world::rollout::{
    evaluate, evaluation_worlds, record_step, rollout, start_worlds, Policy,
};
use uavmeta_world::validate::Validator;
use uavmeta_world::world::{Move, World};

fn config(world_toml: &str) -> Config {
    Config::from_toml_str(&format!("[world]\n{world_toml}"), "team.toml", &[])
        .expect("test config is valid")
}

/// Two UAVs over two devices at (2, 3) and (7, 7), both starting on the first.
const TEAM: &str = "devices = 2\ndevice_cells = [[2, 3], [7, 7]]\nstart_cell = [2, 3]\nuavs = 2";

fn team(world_toml: &str, task: &TaskConfig) -> World {
    World::new(&config(world_toml).world, task, 7)
}

fn act(world: &World, mv: Move, target: usize) -> usize {
    world.layout().action(mv.index(), target)
}

fn risky(probability: f64) -> RiskyRegion {
    RiskyRegion {
        x0: 0,
        y0: 0,
        x1: 4,
        y1: 4,
        penalty: 300.0,
        probability,
    }
}

#[test]
fn two_uavs_on_one_device_restart_its_age_once_and_both_pay() {
    let task = TaskConfig::one_off(300.0, None);
    let mut w = team(TEAM, &task);
    let one = World::new(&config(&TEAM.replace("uavs = 2", "")).world, &task, 7);
    let (alone, _) = one.transmission_at((2, 3), 0, None);
    let hover = act(&w, Move::Hover, 0);
    let step = w.step_team(&[hover, hover]);
    assert_eq!(step.power_mw, 2.0 * alone);
    assert_eq!(w.aoi(), &[1, 2]);
    let mut seen = [0u16; 4];
    w.agent_observation(1, &mut seen);
    assert_eq!(seen, [2, 3, 1, 2]);
    // AoI 1 + 2, then 150 per milliwatt of the two transmissions.
    assert_eq!(step.reward, -(3.0 + 150.0 * 2.0 * alone));
    assert_eq!(step.outages, 0);
}

#[test]
fn the_idle_target_costs_nothing_and_serves_no_one() {
    let mut w = team(
        &format!("{TEAM}\nidle_action = true"),
        &TaskConfig::one_off(300.0, None),
    );
    assert_eq!(w.layout().action_count(), 15);
    let idle = act(&w, Move::Hover, 2);
    assert_eq!(w.layout().served(idle), None);
    let step = w.step_team(&[idle, idle]);
    assert_eq!((step.power_mw, step.reward), (0.0, -4.0));
    assert_eq!(w.aoi(), &[2, 2]);
}

#[test]
fn moves_of_two_cells_stop_at_the_edge() {
    let mut w = team(
        &format!("{TEAM}\nstep_cells = 2"),
        &TaskConfig::one_off(0.0, None),
    );
    w.step_team(&[act(&w, Move::West, 0), act(&w, Move::North, 0)]);
    assert_eq!((w.uav_cell(0), w.uav_cell(1)), ((0, 3), (2, 5)));
    w.step_team(&[act(&w, Move::West, 0), act(&w, Move::South, 0)]);
    assert_eq!((w.uav_cell(0), w.uav_cell(1)), ((0, 3), (2, 3)));
}

#[test]
fn rain_fails_only_the_transmission_of_the_uav_inside_it() {
    let zone = RainZone {
        x0: 0,
        y0: 0,
        x1: 2,
        y1: 2,
    };
    let mut w = team(TEAM, &TaskConfig::one_off(300.0, Some(zone)));
    // UAV 0 to (2, 2), in rain; UAV 1 stays at (2, 3), in the clear.
    w.step_team(&[act(&w, Move::South, 0), act(&w, Move::Hover, 0)]);
    let step = w.step_team(&[act(&w, Move::Hover, 1), act(&w, Move::Hover, 0)]);
    assert_eq!(step.outages, 1);
    // Device 1 was only served from the rain: it ages, device 0 restarts.
    assert_eq!(w.aoi(), &[1, 3]);
}

#[test]
fn the_risky_penalty_is_drawn_in_the_region_and_expected_in_evaluation() {
    let task = TaskConfig {
        risky: Some(risky(1.0)),
        ..TaskConfig::one_off(0.0, None)
    };
    let mut w = team(TEAM, &task);
    let step = w.step_team(&[act(&w, Move::Hover, 0), act(&w, Move::Hover, 1)]);
    assert_eq!(step.penalty, 600.0);

    let idle_task = TaskConfig {
        risky: Some(risky(1.0)),
        ..task.clone()
    };
    let mut w = team(&format!("{TEAM}\nidle_action = true"), &idle_task);
    let step = w.step_team(&[act(&w, Move::Hover, 2), act(&w, Move::Hover, 0)]);
    assert_eq!(step.penalty, 300.0, "no transmission, no penalty");

    let task = TaskConfig {
        risky: Some(risky(0.1)),
        ..task
    };
    let mut w = team(TEAM, &task);
    assert!(!w.is_deterministic());
    let mut expected = team(TEAM, &task).expecting_risk();
    assert!(expected.is_deterministic());
    let step = expected.step_team(&[act(&w, Move::Hover, 0), act(&w, Move::Hover, 0)]);
    assert!((step.penalty - 60.0).abs() < 1e-12);
    // Drawn: 0 or 300 a transmission, and about a tenth of them over many steps.
    let mut charged = 0;
    for _ in 0..2000 {
        let step = w.step_team(&[act(&w, Move::Hover, 0), act(&w, Move::Hover, 0)]);
        assert!([0.0, 300.0, 600.0].contains(&step.penalty));
        charged += (step.penalty / 300.0) as u32;
        if step.truncated {
            w.reset();
        }
    }
    assert!((300..500).contains(&charged), "{charged} of 4000");
}

#[test]
fn risky_draws_never_shift_the_start_cells() {
    let toml = "devices = 2\ndevice_cells = [[2, 3], [7, 7]]\nuavs = 2";
    let task = TaskConfig {
        risky: Some(risky(0.5)),
        ..TaskConfig::one_off(0.0, None)
    };
    let starts = |steps: usize| {
        let mut w = team(toml, &task);
        for _ in 0..steps {
            w.step_team(&[act(&w, Move::Hover, 0), act(&w, Move::Hover, 1)]);
        }
        w.reset();
        (w.uav_cell(0), w.uav_cell(1))
    };
    assert_eq!(starts(0), starts(37));
}

#[test]
fn exact_evaluation_runs_every_joint_start_or_a_fixed_sample() {
    let toml = "devices = 2\ndevice_cells = [[2, 3], [7, 7]]\nuavs = 2";
    let task = TaskConfig::one_off(300.0, None);
    let worlds = start_worlds(&team(toml, &task));
    assert_eq!(worlds.len(), 10_000);
    let joint: HashSet<_> = worlds
        .iter()
        .map(|w| (w.uav_cell(0), w.uav_cell(1)))
        .collect();
    assert_eq!(joint.len(), 10_000);
    let mut again = worlds[1234].clone();
    again.reset();
    assert_eq!(
        (again.uav_cell(0), again.uav_cell(1)),
        (worlds[1234].uav_cell(0), worlds[1234].uav_cell(1))
    );

    let three = format!("{toml}\nuavs = 3").replace("uavs = 2\n", "");
    let sample = |seed| start_worlds(&World::new(&config(&three).world, &task, seed));
    let (a, b) = (sample(1), sample(2));
    assert_eq!(a.len(), MAX_JOINT_STARTS);
    let cells = |ws: &[World]| -> Vec<_> {
        ws.iter()
            .map(|w| (0..3).map(|u| w.uav_cell(u)).collect::<Vec<_>>())
            .collect()
    };
    assert_eq!(
        cells(&a),
        cells(&b),
        "the sample does not depend on the world's seed"
    );

    let risky_task = TaskConfig {
        risky: Some(risky(0.1)),
        ..task
    };
    let worlds = evaluation_worlds(&config(toml).world, &risky_task, 10, 3);
    assert_eq!(
        worlds.len(),
        10_000,
        "the expected penalty keeps evaluation exact"
    );
}

#[test]
fn heuristics_claim_what_an_earlier_uav_serves() {
    let toml = "devices = 10\nuavs = 3";
    let task = TaskConfig::one_off(300.0, None);
    for policy in [&mut StalestPolicy as &mut dyn Policy, &mut GreedyPolicy] {
        let mut w = team(toml, &task);
        let mut actions = [0; 3];
        for _ in 0..100 {
            policy.act_team(&w, &mut actions);
            let served: HashSet<_> = actions.iter().map(|&a| w.layout().device(a)).collect();
            assert_eq!(served.len(), 3, "{actions:?}");
            w.step_team(&actions);
        }
    }
}

#[test]
fn a_team_beats_one_uav_with_the_same_heuristic() {
    let one = config("devices = 10");
    let two = config("devices = 10\nuavs = 2");
    let task = TaskConfig::one_off(300.0, None);
    let alone = evaluate(&one.world, &task, &mut GreedyPolicy, 1, 0)
        .ret
        .mean;
    let pair = evaluate(&two.world, &task, &mut GreedyPolicy, 1, 0)
        .ret
        .mean;
    assert!(pair > alone, "two UAVs {pair}, one {alone}");
}

/// A policy of one UAV, as a learned network is.
struct OneUav;

impl Policy for OneUav {
    fn act(&mut self, _: &World) -> usize {
        0
    }
}

#[test]
fn only_team_policies_fly_a_team() {
    let two = config("devices = 10\nuavs = 2");
    for spec in ["random", "stalest", "greedy", "planner", "eps:0.3"] {
        let spec: PolicySpec = spec.parse().unwrap();
        assert!(spec.build(&two, 0, None).is_ok(), "{spec}");
    }
    let error = PolicySpec::Greedy
        .for_world(&two, Box::new(OneUav))
        .err()
        .unwrap();
    assert!(error.to_string().contains("world.uavs = 2"), "{error}");
    let error = two.require_one_uav("`uavmeta collect`").unwrap_err();
    assert!(error.to_string().contains("world.uavs"), "{error}");
}

#[test]
fn a_one_uav_world_serialises_and_hashes_as_before_teams() {
    let config = Config::default();
    let text = config.to_toml_string();
    for key in ["uavs", "idle_action", "step_cells", "risky"] {
        assert!(!text.contains(key), "{key} in\n{text}");
    }
    for bad in ["uavs = 0", "uavs = 9", "step_cells = 0"] {
        let error = Config::from_toml_str(&format!("[world]\n{bad}"), "bad.toml", &[]);
        let error = error.unwrap_err().to_string();
        let key = bad.split(' ').next().unwrap();
        assert!(error.contains(key), "{bad}: {error}");
    }
    let off_grid = "[[tasks]]\nname = \"r\"\nlambda = 1.0\nrole = \"meta-test\"\n\
                    risky = { x0 = 8, y0 = 0, x1 = 11, y1 = 4, penalty = 300.0, probability = 0.1 }";
    let error = Config::from_toml_str(off_grid, "bad.toml", &[])
        .unwrap_err()
        .to_string();
    assert!(error.contains("tasks[0].risky"), "{error}");
    let inside = off_grid.replace("x1 = 11", "x1 = 9");
    let bad_values = [
        ("probability = 0.1", "probability = 1.5", "probability"),
        ("penalty = 300.0", "penalty = -1.0", "penalty"),
    ];
    for (good, bad, key) in bad_values {
        let text = inside.replace(good, bad);
        let error = Config::from_toml_str(&text, "bad.toml", &[])
            .unwrap_err()
            .to_string();
        assert!(
            error.contains("risky") && error.contains(key),
            "{bad}: {error}"
        );
    }
}

#[test]
fn the_validator_accepts_a_penalised_step_of_a_risky_task() {
    let config = config("devices = 2\ndevice_cells = [[2, 3], [7, 7]]\nstart_cell = [2, 3]");
    let task = TaskConfig {
        risky: Some(risky(0.5)),
        ..TaskConfig::one_off(300.0, None)
    };
    let mut w = World::new(&config.world, &task, 11);
    let mut validator = Validator::new(&config.world, &task);
    let mut penalised = 0;
    let hover = act(&w, Move::Hover, 0);
    for _ in 0..50 {
        let t: Transition = record_step(&mut w, hover);
        let clear = World::new(&config.world, &TaskConfig::one_off(300.0, None), 0);
        let mut next = vec![0; 4];
        let plain = clear.outcome(&t.obs, usize::from(t.action), false, false, &mut next);
        penalised += u32::from(plain.map(|r| r as f32) != Some(t.reward));
        assert!(validator.check((&t).into()).is_ok(), "{t:?}");
    }
    assert!(penalised > 0);
}

/// configs/multi-uav.toml, the authors' setting (docs/MODEL.md section 11): every task flies its
/// own layout (the listed cells, or one drawn from its seed), and on each the greedy team beats
/// the random one over the same 100 episodes.
#[test]
fn the_authors_tasks_each_fly_their_own_layout() {
    let path = concat!(env!("CARGO_MANIFEST_DIR"), "/../configs/multi-uav.toml");
    let config = Config::load(std::path::Path::new(path), &[]).expect("configs/multi-uav.toml");
    assert_eq!((config.world.uavs, config.tasks.len()), (2, 16));
    let mut layouts = HashSet::new();
    for task in &config.tasks {
        let world = World::new(&config.world, task, 0);
        if let Some(cells) = &task.device_cells {
            let listed: Vec<(u32, u32)> = cells.iter().map(|c| (c[0], c[1])).collect();
            assert_eq!(world.device_cells(), listed, "{}", task.name);
        } else {
            assert!(
                task.layout_seed.is_some(),
                "{}: a layout of its own",
                task.name
            );
        }
        layouts.insert(world.device_cells().to_vec());
        let score = |policy: &mut dyn Policy| {
            let episodes = rollout(&config.world, task, policy, 100, 1, |_, _| {});
            PolicyMetrics::from_episodes(&episodes).ret.mean
        };
        let (greedy, random) = (score(&mut GreedyPolicy), score(&mut RandomPolicy::new(1)));
        assert!(
            greedy > random,
            "{}: greedy {greedy} against random {random}",
            task.name
        );
    }
    // Their code gives train-1 and train-4 one layout, train-2 and train-8 another, and test-0
    // train-6's.
    assert_eq!(layouts.len(), 13);
}

/// Greedy prices a risky region's expected penalty into a step's cost and flies to a cell outside
/// the region that its moves reach: a UAV two cells a move, starting inside the region next to a
/// device just outside it, leaves and serves that device without ever paying the penalty, where
/// hovering beside it inside the region (the device's cell out of reach by whole moves) would
/// never serve it.
#[test]
fn greedy_serves_from_outside_a_risky_region() {
    let toml = "devices = 1\ndevice_cells = [[2, 3]]\nstart_cell = [3, 4]\nstep_cells = 2\n\
                idle_action = true\nnoise_dbm = -90.0";
    let task = TaskConfig {
        risky: Some(RiskyRegion {
            x0: 3,
            y0: 2,
            x1: 6,
            y1: 6,
            penalty: 3000.0,
            probability: 0.1,
        }),
        ..TaskConfig::one_off(35.0, None)
    };
    let mut w = World::new(&config(toml).world, &task, 0).expecting_risk();
    w.reset();
    let (mut penalty, mut served) = (0.0, 0);
    for _ in 0..100 {
        let action = GreedyPolicy.act(&w);
        let step = w.step(action);
        penalty += step.penalty;
        served += usize::from(w.aoi()[0] == 1);
    }
    assert_eq!(penalty, 0.0);
    // Serving costs about 22 reward units from beside the device: greedy serves once its age
    // is past that, a few times an episode.
    assert!(served >= 3, "served {served} times in 100 steps");
}
