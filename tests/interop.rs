//! `uavmeta dataset export` and `inspect` as a user runs them, and the exports loaded by their
//! real consumers: numpy, d3rlpy (its MDPDataset and a few DiscreteCQL steps) and Minari, run by
//! tests/interop_check.py in the libtorch virtualenv's Python, where `make interop` installs them.
//! Without them the Python half is skipped with the reason, except under `CI=true`, where it
//! fails.

mod support;

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

use uavmeta_proto::dataset::DatasetReader;

const CONFIG: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/configs/default.toml");

/// Whole episodes of 20 steps from a seeded random policy: ten of them.
const SMALL: &[&str] = &["world.horizon=20", "collect.transitions=200"];
const SHOTS: usize = 50;
const SHOT_SEED: u64 = 11;

fn uavmeta(dir: &Path, args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_uavmeta"))
        .current_dir(dir)
        .args(args)
        .output()
        .expect("run uavmeta")
}

fn stdout(output: Output) -> String {
    assert!(
        output.status.success(),
        "uavmeta failed: {}",
        String::from_utf8_lossy(&output.stderr)
    );
    String::from_utf8(output.stdout).expect("utf-8 output")
}

/// The stderr of a command that must fail cleanly: exit code 1 and an error, not a panic.
fn failure(output: Output) -> String {
    let stderr = String::from_utf8_lossy(&output.stderr).into_owned();
    assert_eq!(output.status.code(), Some(1), "{stderr}");
    assert!(!stderr.contains("panicked"), "{stderr}");
    assert!(stderr.starts_with("uavmeta: "), "{stderr}");
    stderr
}

/// A random-policy dataset of task lambda-300 in `dir`, its config saved beside it.
fn collect(dir: &Path) -> PathBuf {
    let mut args = vec!["collect", "--config", CONFIG];
    for set in SMALL {
        args.extend(["--set", set]);
    }
    args.extend(["--task", "lambda-300", "--policy", "random", "--seed", "3"]);
    args.extend(["--out", "data/lambda-300.uavds"]);
    stdout(uavmeta(dir, &args));
    dir.join("data/lambda-300.uavds")
}

fn export(dir: &Path, format: &str, out: &str, extra: &[&str]) -> Output {
    let mut args = vec!["dataset", "export", "--dataset", "data/lambda-300.uavds"];
    args.extend(["--format", format, "--out", out]);
    args.extend(extra);
    uavmeta(dir, &args)
}

#[test]
fn inspect_prints_the_header_counts_returns_and_action_histogram() {
    let dir = tempfile::tempdir().expect("temp dir");
    let file = collect(dir.path());
    let text = stdout(uavmeta(
        dir.path(),
        &["dataset", "inspect", "data/lambda-300.uavds"],
    ));
    let source = DatasetReader::open(&file).unwrap();
    let total: f64 = source
        .transitions()
        .iter()
        .map(|t| f64::from(t.reward))
        .sum();
    let lines: Vec<&str> = text.lines().collect();
    assert!(lines[0].ends_with("every CRC32 valid"), "{text}");
    assert!(
        lines[1].contains("`lambda-300`") && lines[1].contains("lambda = 300, no rain"),
        "{text}"
    );
    assert!(
        text.contains("200 (actors: 1, episodes: 10) in 10 runs of consecutive steps, 10 of them whole episodes"),
        "{text}"
    );
    // Ten whole episodes: their mean return is the total over ten.
    assert!(
        text.contains(&format!("10 whole episodes: mean {:.2} ±", total / 10.0)),
        "{text}"
    );
    // The histogram: a row per move, in action order, each ending in its total; the totals add
    // up to 200.
    let moves = ["north", "south", "east", "west", "hover"];
    let rows: Vec<&str> = lines
        .iter()
        .copied()
        .filter(|l| moves.contains(&l.split_whitespace().next().unwrap_or("")))
        .collect();
    let firsts: Vec<&str> = rows
        .iter()
        .filter_map(|l| l.split_whitespace().next())
        .collect();
    assert_eq!(firsts, moves, "{text}");
    let totals: Vec<u64> = rows
        .iter()
        .map(|l| l.split_whitespace().last().unwrap().parse().unwrap())
        .collect();
    assert_eq!(totals.iter().sum::<u64>(), 200, "{text}");
    // And the store's checks, run on the file.
    assert!(
        text.contains("every transition passes the store's checks"),
        "{text}"
    );
}

#[test]
fn bad_input_is_an_error_naming_the_file_or_value() {
    let dir = tempfile::tempdir().expect("temp dir");
    let file = collect(dir.path());
    let d = dir.path();

    let missing = failure(uavmeta(d, &["dataset", "inspect", "data/none.uavds"]));
    assert!(
        missing.contains("data/none.uavds: cannot read"),
        "{missing}"
    );
    let args = [
        "dataset",
        "export",
        "--dataset",
        "data/none.uavds",
        "--format",
        "npz",
        "--out",
        "x.npz",
    ];
    let missing = failure(uavmeta(d, &args));
    assert!(
        missing.contains("data/none.uavds: cannot read") && !missing.contains("config"),
        "{missing}"
    );

    let shots = failure(export(d, "npz", "x.npz", &["--shots", "201"]));
    assert!(
        shots.contains("data/lambda-300.uavds: asked for 201 distinct transitions: expected between 1 and the 200 available"),
        "{shots}"
    );

    stdout(export(d, "npz", "x.npz", &[]));
    let exists = failure(export(d, "npz", "x.npz", &[]));
    assert!(exists.contains("x.npz: already exists"), "{exists}");
    stdout(export(d, "minari", "root", &[]));
    let exists = failure(export(d, "minari", "root", &[]));
    assert!(
        exists.contains("root/uavmeta/lambda-300-v0: already exists"),
        "{exists}"
    );
    let id = failure(export(d, "minari", "root", &["--id", "uavmeta/x.y-v0"]));
    assert!(id.contains("`uavmeta/x.y-v0`: expected"), "{id}");

    // clap refuses an unknown format before uavmeta runs, with its usage error.
    let format = uavmeta(
        d,
        &[
            "dataset",
            "export",
            "--dataset",
            "data/lambda-300.uavds",
            "--format",
            "hdf5",
            "--out",
            "y",
        ],
    );
    let stderr = String::from_utf8_lossy(&format.stderr);
    assert_eq!(format.status.code(), Some(2), "{stderr}");
    assert!(
        stderr.contains("unknown export format `hdf5`: expected `minari` or `npz`"),
        "{stderr}"
    );

    let mut bytes = std::fs::read(&file).unwrap();
    let last = bytes.len() - 10;
    bytes[last] ^= 0xff;
    std::fs::write(&file, bytes).unwrap();
    for output in [
        uavmeta(d, &["dataset", "inspect", "data/lambda-300.uavds"]),
        export(d, "npz", "z.npz", &[]),
    ] {
        let damaged = failure(output);
        assert!(
            damaged.contains("data/lambda-300.uavds: offset") && damaged.contains("CRC32"),
            "{damaged}"
        );
    }
    assert!(!d.join("z.npz").exists());
}

/// A run's dataset (`RUN/datasets/TASK.uavds`) takes the run's `config.toml`, as `export --help`
/// says, for `export` as for `inspect`; with neither config there, the error names the file to
/// pass.
#[test]
fn a_runs_dataset_exports_with_the_runs_config() {
    let dir = tempfile::tempdir().expect("temp dir");
    let d = dir.path();
    let file = collect(d);
    std::fs::create_dir_all(d.join("run/datasets")).unwrap();
    std::fs::rename(&file, d.join("run/datasets/lambda-300.uavds")).unwrap();
    let beside = d.join("data/lambda-300.uavds.config.toml");
    let args = |out: &'static str| {
        [
            "dataset",
            "export",
            "--dataset",
            "run/datasets/lambda-300.uavds",
            "--format",
            "npz",
            "--out",
            out,
        ]
    };
    let missing = failure(uavmeta(d, &args("a.npz")));
    assert!(
        missing.contains("run/datasets/lambda-300.uavds.config.toml: cannot read")
            && missing.contains("pass --config FILE"),
        "{missing}"
    );
    std::fs::rename(&beside, d.join("run/config.toml")).unwrap();
    let text = stdout(uavmeta(d, &args("b.npz")));
    assert!(
        text.contains("200 transitions of task `lambda-300`"),
        "{text}"
    );
    stdout(uavmeta(
        d,
        &["dataset", "inspect", "run/datasets/lambda-300.uavds"],
    ));
}

#[test]
fn exports_load_in_numpy_d3rlpy_and_minari_as_the_source() {
    let python = support::venv_python();
    if !support::python_imports(&python, "numpy, d3rlpy, minari, pyarrow", "make interop") {
        return;
    }
    let dir = tempfile::tempdir().expect("temp dir");
    let d = dir.path();
    let file = collect(d);
    let (n, seed) = (SHOTS.to_string(), SHOT_SEED.to_string());
    let shots = ["--shots", n.as_str(), "--seed", seed.as_str()];
    stdout(export(d, "npz", "full.npz", &[]));
    stdout(export(d, "npz", "shots.npz", &shots));
    let printed = stdout(export(d, "minari", "minari", &[]));
    assert!(
        printed.contains("200 steps of task `lambda-300` in 10 episodes"),
        "{printed}"
    );
    stdout(export(d, "minari", "minari", &shots));

    // The source, and the very shots `uavmeta train --shots 50 --seed 11` trains on.
    let source = DatasetReader::open(&file).unwrap();
    let expected = serde_json::json!({
        "full": source.transitions(),
        "shots": source.shots(SHOTS, SHOT_SEED).unwrap(),
        "action_count": 50,
        "observation_len": 12,
        "task": "lambda-300",
        "lambda": 300.0,
        "rain": null,
        "minari_full": "uavmeta/lambda-300-v0",
        "minari_shots": "uavmeta/lambda-300-50shots-v0",
    });
    std::fs::write(d.join("expected.json"), expected.to_string()).unwrap();

    let script = concat!(env!("CARGO_MANIFEST_DIR"), "/tests/interop_check.py");
    let out = Command::new(&python)
        .arg(script)
        .arg(d)
        .output()
        .expect("run python");
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{script}:\n{stdout}{}",
        String::from_utf8_lossy(&out.stderr)
    );
    eprintln!("{stdout}");
    assert!(
        stdout.contains("full.npz 200 transitions in 10 runs")
            && stdout.contains("Minari 10 + ")
            && stdout.contains("10 truncations"),
        "{stdout}"
    );
}
