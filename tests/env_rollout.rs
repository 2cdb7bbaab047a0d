//! `uavmeta env rollout` as a user runs it: the table, `--trace`, `--json`, determinism and errors.

use std::io::Write;
use std::process::{Command, Output};

const WORLD: &str =
    "[world]\ndevices = 3\ndevice_cells = [[0, 0], [9, 9], [5, 2]]\nhorizon = 7\n\n\
                     [[tasks]]\nname = \"wet\"\nlambda = 300.0\nrole = \"meta-test\"\n\
                     rain = { x0 = 0, y0 = 0, x1 = 4, y1 = 9 }\n";

fn config_file() -> tempfile::NamedTempFile {
    let mut file = tempfile::Builder::new()
        .suffix(".toml")
        .tempfile()
        .expect("temp file");
    file.write_all(WORLD.as_bytes()).expect("write config");
    file
}

fn rollout(config: &tempfile::NamedTempFile, extra: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_uavmeta"))
        .args(["env", "rollout", "--config"])
        .arg(config.path())
        .args(["--task", "wet", "--seed", "3"])
        .args(extra)
        .args(if extra.contains(&"--episodes") {
            &[][..]
        } else {
            &["--episodes", "4"][..]
        })
        .output()
        .expect("run uavmeta")
}

fn stdout(output: &Output) -> String {
    assert!(
        output.status.success(),
        "uavmeta failed: {}",
        String::from_utf8_lossy(&output.stderr)
    );
    String::from_utf8(output.stdout.clone()).expect("utf-8 output")
}

#[test]
fn table_lists_every_episode_and_the_means() {
    let config = config_file();
    let text = stdout(&rollout(&config, &["--policy", "random"]));
    let lines: Vec<&str> = text.lines().collect();
    assert!(
        lines[0].starts_with("random on task wet (lambda = 300)"),
        "{text}"
    );
    assert_eq!(lines.len(), 2 + 4 + 1, "{text}");
    for (i, row) in lines[2..6].iter().enumerate() {
        assert_eq!(
            row.split_whitespace().next(),
            Some(i.to_string().as_str()),
            "{row}"
        );
    }
    assert!(lines[6].starts_with("mean ± 95% CI: return "), "{text}");
    assert_eq!(
        text,
        stdout(&rollout(&config, &["--policy", "random"])),
        "same seed, same table"
    );
}

#[test]
fn trace_has_one_object_per_step_and_agrees_with_the_summary() {
    let config = config_file();
    let output = rollout(&config, &["--policy", "stalest", "--trace"]);
    let text = stdout(&output);
    let steps: Vec<serde_json::Value> = text
        .lines()
        .map(|l| serde_json::from_str(l).expect("each trace line is JSON"))
        .collect();
    assert_eq!(steps.len(), 4 * 7);
    assert!(
        String::from_utf8_lossy(&output.stderr).contains("mean ± 95% CI"),
        "the table goes to stderr"
    );
    for (i, step) in steps.iter().enumerate() {
        assert_eq!(step["episode"], i / 7);
        assert_eq!(step["t"], i % 7);
        assert_eq!(step["aoi"].as_array().expect("aoi vector").len(), 3);
        let outage = step["outage"].as_bool().expect("outage flag");
        assert_eq!(
            outage,
            step["position"][0].as_u64().expect("x") <= 4,
            "rain covers x <= 4: {step}"
        );
        let action = step["action"].as_u64().expect("action");
        assert_eq!(step["device"], action % 3);
        assert!(step.get("uavs").is_none(), "one UAV: no team part: {step}");
    }

    let summary: serde_json::Value = serde_json::from_str(&stdout(&rollout(
        &config,
        &["--policy", "stalest", "--json"],
    )))
    .expect("JSON");
    for (e, episode) in summary["episodes"]
        .as_array()
        .expect("episodes")
        .iter()
        .enumerate()
    {
        let of_episode = || steps.iter().filter(move |s| s["episode"] == e);
        let ret: f64 = of_episode()
            .map(|s| s["reward"].as_f64().expect("reward"))
            .sum();
        let outages = of_episode().filter(|s| s["outage"] == true).count();
        assert!((ret - episode["ret"].as_f64().expect("ret")).abs() < 1e-9);
        assert_eq!(episode["outages"], outages);
    }
    assert_eq!(summary["mean"]["episodes"], 4);
    assert_eq!(summary["policy"], "stalest");
}

/// In a team each trace line holds every UAV's cell, action, move and target, UAV 0's also at the
/// top level; each UAV's next cell is its move from this one, two cells a move.
#[test]
fn a_team_trace_has_each_uavs_part_of_every_step() {
    let config = config_file();
    let team = [
        "world.uavs=2",
        "world.step_cells=2",
        "world.idle_action=true",
    ];
    let mut args = vec!["--policy", "greedy", "--trace"];
    team.iter().for_each(|s| args.extend(["--set", s]));
    let steps: Vec<serde_json::Value> = stdout(&rollout(&config, &args))
        .lines()
        .map(|l| serde_json::from_str(l).expect("each trace line is JSON"))
        .collect();
    assert_eq!(steps.len(), 4 * 7);
    let cell = |v: &serde_json::Value| (v[0].as_i64().unwrap(), v[1].as_i64().unwrap());
    let mut moved = 0;
    for pair in steps.windows(2) {
        let (now, next) = (&pair[0], &pair[1]);
        let uavs = now["uavs"].as_array().expect("every UAV's part");
        assert_eq!(uavs.len(), 2, "{now}");
        for key in ["position", "action", "move", "device"] {
            assert_eq!(uavs[0][key], now[key], "{key}: {now}");
        }
        for (u, part) in uavs.iter().enumerate() {
            let action = part["action"].as_u64().expect("action");
            assert_eq!(part["device"], action % 4, "targets: 3 devices and none");
            if next["episode"] != now["episode"] {
                continue;
            }
            let ((x, y), (nx, ny)) = (cell(&part["position"]), cell(&next["uavs"][u]["position"]));
            let (dx, dy) = (nx - x, ny - y);
            let step = match part["move"].as_str().expect("move") {
                "hover" => (0, 0),
                "east" => (2, 0),
                "west" => (-2, 0),
                "north" => (0, 2),
                "south" => (0, -2),
                other => panic!("move {other}"),
            };
            // A move stops at the grid's edge.
            let within = |d: i64, s: i64, at: i64| {
                d == s || (d.abs() < s.abs() && !(0..=9).contains(&(at + s)))
            };
            assert!(
                within(dx, step.0, x) && within(dy, step.1, y),
                "UAV {u}: {part} -> {next}"
            );
            moved += usize::from(dx != 0 || dy != 0);
        }
    }
    assert!(moved > 0, "the UAVs moved");
}

#[test]
fn bad_input_fails_with_a_clear_message() {
    let config = config_file();
    let mut actions = tempfile::NamedTempFile::new().expect("temp file");
    actions.write_all(b"4\n99\n").expect("write actions");
    let replay = format!("actions:{}", actions.path().display());
    for (args, expected) in [
        (
            vec!["--policy", replay.as_str()],
            "line 2: `99`: expected an action index below 15",
        ),
        (vec!["--policy", "eps:-1"], "is not a probability"),
        (vec!["--episodes", "0"], "--episodes 0"),
        (vec!["--set", "world.devices=200"], "world.devices"),
    ] {
        let output = rollout(&config, &args);
        assert!(!output.status.success(), "{args:?} should fail");
        let stderr = String::from_utf8_lossy(&output.stderr);
        assert!(stderr.contains(expected), "{args:?}: {stderr}");
    }
}

/// `--exact` runs one episode per start cell where the world is deterministic (the named rain
/// task: 100 cells, whatever `--episodes`), and the Monte-Carlo episodes where a one-off task's
/// rain moves (`--rain-moves-every`, which names the task after it).
#[test]
fn exact_evaluation_covers_every_start_cell_unless_the_rain_moves() {
    let config = config_file();
    let json = |extra: &[&str]| -> serde_json::Value {
        let mut args = vec!["env", "rollout", "--json", "--exact", "--episodes", "3"];
        args.extend_from_slice(extra);
        let output = Command::new(env!("CARGO_BIN_EXE_uavmeta"))
            .args(&args)
            .arg("--config")
            .arg(config.path())
            .output()
            .expect("run uavmeta");
        serde_json::from_str(&stdout(&output)).expect("one JSON summary")
    };
    let fixed = json(&["--task", "wet"]);
    assert_eq!(fixed["episodes"].as_array().map(Vec::len), Some(100));
    let moving = json(&[
        "--lambda",
        "300",
        "--rain",
        "0,0,4,9",
        "--rain-moves-every",
        "2",
    ]);
    assert_eq!(moving["task"], "lambda-300-rain-0-0-4-9-moves-2");
    assert_eq!(moving["episodes"].as_array().map(Vec::len), Some(3));
    // The rain that moves does not stay on the western half, where the fixed one keeps it.
    let outages = |v: &serde_json::Value| v["mean"]["outages"]["mean"].as_f64().expect("outages");
    assert!(outages(&moving) != outages(&fixed), "{moving}");
}

/// `uavmeta env rollout ... | head -1`: a reader that has gone ends the command quietly, by
/// SIGPIPE as for any Unix tool, not with a panic. The pipe's read end is closed before the
/// command starts, so its first line already meets the closed pipe.
#[test]
fn a_closed_pipe_ends_the_command_quietly() {
    use std::os::unix::process::ExitStatusExt;
    let config = config_file();
    let (reader, writer) = std::io::pipe().expect("pipe");
    drop(reader);
    let output = Command::new(env!("CARGO_BIN_EXE_uavmeta"))
        .args(["env", "rollout", "--config"])
        .arg(config.path())
        .args(["--task", "wet", "--seed", "3", "--episodes", "4"])
        .stdout(writer)
        .output()
        .expect("run uavmeta");
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(!stderr.contains("panicked"), "{stderr}");
    assert_eq!(
        output.status.signal(),
        Some(libc::SIGPIPE),
        "{:?}: {stderr}",
        output.status
    );
}
