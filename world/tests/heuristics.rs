//! The heuristic policies' choices in hand-built states, and the `--policy` parser's errors.

use std::io::Write;

use uavmeta_proto::config::{Config, RainZone, TaskConfig};
use uavmeta_world::heuristics::{
    EpsilonPolicy, GreedyPolicy, PolicySpec, RandomPolicy, StalestPolicy,
};
use uavmeta_world::rollout::Policy;
use uavmeta_world::world::{Move, World};

fn world(world_toml: &str, lambda: f64, rain: Option<RainZone>) -> World {
    let cfg = Config::from_toml_str(&format!("[world]\n{world_toml}"), "test.toml", &[])
        .expect("valid test config");
    World::new(&cfg.world, &TaskConfig::one_off(lambda, rain), 0)
}

/// (move, device) of an action index.
fn split(world: &World, action: usize) -> (Move, usize) {
    (
        Move::from_index(world.layout().split(action).0),
        world.layout().device(action),
    )
}

#[test]
fn stalest_serves_the_oldest_and_flies_x_first() {
    let mut w = world(
        "devices = 3\ndevice_cells = [[5, 1], [2, 8], [0, 0]]\nstart_cell = [3, 3]",
        0.0,
        None,
    );
    // All AoI equal: ties go to device 0 at (5, 1): east first.
    assert_eq!(split(&w, StalestPolicy.act(&w)), (Move::East, 0));
    // Serve 0 and 2; device 1 at (2, 8) is then the stalest: west first, then north.
    w.step(Move::Hover.index() * 3);
    w.step(Move::West.index() * 3 + 2);
    assert_eq!(w.uav(), (2, 3));
    assert_eq!(split(&w, StalestPolicy.act(&w)), (Move::North, 1));
    let mut w = world(
        "devices = 1\ndevice_cells = [[4, 4]]\nstart_cell = [4, 4]",
        0.0,
        None,
    );
    assert_eq!(split(&w, StalestPolicy.act(&w)), (Move::Hover, 0));
    let a = StalestPolicy.act(&w);
    w.step(a);
    assert_eq!(w.uav(), (4, 4));
}

#[test]
fn stalest_weighs_aoi_by_delta() {
    let mut w = world(
        "devices = 2\ndevice_cells = [[0, 0], [9, 9]]\nstart_cell = [0, 0]\ndelta = [1.0, 3.0]",
        0.0,
        None,
    );
    w.step(Move::Hover.index() * 2 + 1);
    w.step(Move::Hover.index() * 2 + 1);
    // A = [3, 1]: delta-weighted 3 vs 3, a tie, goes to device 0; one more step makes it 4 vs 6.
    assert_eq!(split(&w, StalestPolicy.act(&w)).1, 0);
    w.step(Move::Hover.index() * 2);
    w.step(Move::Hover.index() * 2);
    assert_eq!(w.aoi(), &[1, 3]);
    assert_eq!(split(&w, StalestPolicy.act(&w)).1, 1);
}

#[test]
fn greedy_trades_aoi_against_power() {
    // The UAV hovers on device 0 (0.031 mW); device 1 is 900 m away: 3.1e-9 * (1e4 + 81e4) W =
    // 2.542 mW. With lambda / K = 5 and A_0 = 1, serving device 0 costs S - 1 + 0.155 and serving
    // device 1 costs S - A_1 + 12.71, so greedy switches to device 1 once A_1 > 13.555.
    let mut w = world(
        "devices = 2\ndevice_cells = [[0, 0], [9, 0]]\nstart_cell = [0, 0]",
        10.0,
        None,
    );
    let hover_on_0 = Move::Hover.index() * 2;
    w.step(hover_on_0);
    assert_eq!(
        split(&w, GreedyPolicy.act(&w)),
        (Move::East, 0),
        "serve 0, fly towards the stalest"
    );
    while split(&w, GreedyPolicy.act(&w)).1 == 0 {
        assert_eq!(w.aoi()[0], 1);
        w.step(hover_on_0);
    }
    assert_eq!(w.aoi(), &[1, 14]);
    assert!(w.cost_of(1) < w.cost_of(0));
}

#[test]
fn greedy_avoids_paying_for_an_outage() {
    let rain = Some(RainZone {
        x0: 0,
        y0: 0,
        x1: 0,
        y1: 0,
    });
    let mut w = world(
        "devices = 2\ndevice_cells = [[0, 0], [1, 0]]\nstart_cell = [0, 0]",
        100.0,
        rain,
    );
    w.step(Move::Hover.index() * 2);
    // In rain nothing resets, so the cheapest device is the one needing the least power.
    assert_eq!(split(&w, GreedyPolicy.act(&w)).1, 0);
    assert!(w.cost_of(0) < w.cost_of(1));
}

#[test]
fn random_and_epsilon_are_seeded() {
    let w = world("", 0.0, None);
    let draw = |p: &mut dyn Policy| (0..200).map(|_| p.act(&w)).collect::<Vec<_>>();
    let a = draw(&mut RandomPolicy::new(3));
    assert_eq!(a, draw(&mut RandomPolicy::new(3)));
    assert_ne!(a, draw(&mut RandomPolicy::new(4)));
    assert!(a.iter().all(|&x| x < w.layout().action_count()));
    let distinct: std::collections::BTreeSet<_> = a.iter().collect();
    assert!(
        distinct.len() > 40,
        "200 uniform draws of 50 actions hit {}",
        distinct.len()
    );

    let stalest = StalestPolicy.act(&w);
    assert!(draw(&mut EpsilonPolicy::new(0.0, 1))
        .iter()
        .all(|&x| x == stalest));
    let mixed = draw(&mut EpsilonPolicy::new(0.5, 1));
    let share = mixed.iter().filter(|&&x| x != stalest).count() as f64 / 200.0;
    // P = 0.5 random, and a random draw equals the stalest action 1 time in 50.
    assert!((0.35..0.65).contains(&share), "{share}");
    assert_eq!(mixed, draw(&mut EpsilonPolicy::new(0.5, 1)));
}

#[test]
fn policy_specs_parse_and_print() {
    for (text, spec) in [
        ("random", PolicySpec::Random),
        ("stalest", PolicySpec::Stalest),
        ("greedy", PolicySpec::Greedy),
        ("planner", PolicySpec::Planner),
        ("eps:0.25", PolicySpec::Epsilon(0.25)),
        ("actions:run/a.txt", PolicySpec::Actions("run/a.txt".into())),
    ] {
        let parsed: PolicySpec = text.parse().expect("valid spec");
        assert_eq!(parsed, spec);
        assert_eq!(parsed.to_string(), text);
    }
    for (text, part) in [
        ("stalestt", "expected random, stalest"),
        ("eps:1.5", "`1.5` is not a probability"),
        ("eps:x", "`x` is not a probability"),
        ("actions:", "expected a file"),
        ("dqn:3", "expected random"),
    ] {
        let message = text
            .parse::<PolicySpec>()
            .expect_err("invalid spec")
            .to_string();
        assert!(
            message.contains(text) && message.contains(part),
            "{text}: {message}"
        );
    }
}

fn action_file(text: &str) -> tempfile::NamedTempFile {
    let mut file = tempfile::NamedTempFile::new().expect("temp file");
    file.write_all(text.as_bytes()).expect("write actions");
    file
}

#[test]
fn replay_follows_the_file_across_episodes() {
    let file = action_file("3\n\n49\n0\n");
    let spec = PolicySpec::Actions(file.path().into());
    let mut policy = spec
        .build(&Config::default(), 0, Some(3))
        .expect("three actions suffice");
    let w = world("", 0.0, None);
    assert_eq!([policy.act(&w), policy.act(&w), policy.act(&w)], [3, 49, 0]);
    // Past its end the list plays again from the start (an actor's rollout has no end).
    assert_eq!(policy.act(&w), 3);
}

/// An actor asks for no fixed number of steps: any non-empty list serves it, an empty one is
/// refused rather than replayed.
#[test]
fn replay_for_an_unbounded_rollout_needs_one_action() {
    let file = action_file("7\n");
    let mut policy = PolicySpec::Actions(file.path().into())
        .build(&Config::default(), 0, None)
        .expect("one action suffices");
    let w = world("", 0.0, None);
    assert_eq!([policy.act(&w), policy.act(&w)], [7, 7]);
    let empty = action_file("\n");
    let message = PolicySpec::Actions(empty.path().into())
        .build(&Config::default(), 0, None)
        .err()
        .expect("empty list")
        .to_string();
    assert!(
        message.contains("holds 0 actions") && message.contains("needs 1"),
        "{message}"
    );
}

#[test]
fn replay_errors_name_file_line_and_value() {
    let file = action_file("1\n2\n\nfifty\n");
    let path = file.path().display().to_string();
    let message = PolicySpec::Actions(file.path().into())
        .build(&Config::default(), 0, Some(1))
        .err()
        .expect("bad line")
        .to_string();
    assert!(
        message.contains(&path) && message.contains("line 4") && message.contains("`fifty`"),
        "{message}"
    );

    let file = action_file("1\n50\n");
    let message = PolicySpec::Actions(file.path().into())
        .build(&Config::default(), 0, Some(1))
        .err()
        .expect("out of range")
        .to_string();
    assert!(
        message.contains("line 2") && message.contains("`50`") && message.contains("below 50"),
        "{message}"
    );

    let file = action_file("1\n2\n");
    let message = PolicySpec::Actions(file.path().into())
        .build(&Config::default(), 0, Some(100))
        .err()
        .expect("too short")
        .to_string();
    assert!(
        message.contains("holds 2 actions") && message.contains("needs 100"),
        "{message}"
    );

    let message = PolicySpec::Actions("/nonexistent/actions.txt".into())
        .build(&Config::default(), 0, Some(1))
        .err()
        .expect("missing")
        .to_string();
    assert!(
        message.contains("/nonexistent/actions.txt") && message.contains("cannot read"),
        "{message}"
    );
}
