//! The single-process learning commands as a user runs them, on the shipped default config shrunk
//! with `--set`: `collect`, `train`, `eval`, `meta-train`, `meta-test`, and their errors on bad
//! input (a damaged dataset, an unknown config key, a checkpoint that does not fit).

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

const CONFIG: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/configs/default.toml");

/// Small enough that every command takes well under a second; the world overrides change its
/// hash, so every command of a test passes the same list.
const SMALL: &[&str] = &[
    "world.horizon=20",
    "learner.hidden=[16,16]",
    "learner.eval_episodes=2",
    "collect.transitions=120",
    "collect.dqn.steps=300",
    "collect.dqn.replay_capacity=300",
    "collect.dqn.learning_starts=100",
    "collect.dqn.eps_decay_steps=200",
];

/// The default config meta-trains on eight tasks; these keep `lambda-0` and `lambda-100` by
/// turning the other six into meta-test tasks.
const TWO_META_TRAIN_TASKS: &[&str] = &[
    "tasks.2.role=meta-test",
    "tasks.3.role=meta-test",
    "tasks.4.role=meta-test",
    "tasks.5.role=meta-test",
    "tasks.6.role=meta-test",
    "tasks.7.role=meta-test",
];

/// The columns of `train.csv` that users' scripts read (learner/src/train.rs).
const TRAIN_COLUMNS: &str = "epoch,steps,td_loss,conservative_loss,mean_q,return,return_ci95,aoi,aoi_ci95,power_mw,power_mw_ci95,outages,outages_ci95,episodes,seconds,network_epoch";

/// `uavmeta SUBCOMMAND --config CONFIG [--set KEY=VALUE].. ARGS` run in `dir`, so relative paths
/// are the user's.
fn uavmeta(dir: &Path, subcommand: &str, overrides: &[&str], args: &[&str]) -> Output {
    let mut command = Command::new(env!("CARGO_BIN_EXE_uavmeta"));
    command
        .current_dir(dir)
        .args([subcommand, "--config", CONFIG]);
    for set in overrides {
        command.args(["--set", set]);
    }
    command.args(args).output().expect("run uavmeta")
}

fn stdout(output: &Output) -> String {
    assert!(
        output.status.success(),
        "uavmeta failed: {}",
        String::from_utf8_lossy(&output.stderr)
    );
    String::from_utf8(output.stdout.clone()).expect("utf-8 output")
}

/// The stderr of a command that must fail cleanly: a non-zero exit and an error, not a panic.
fn failure(output: &Output) -> String {
    let stderr = String::from_utf8_lossy(&output.stderr).into_owned();
    assert!(
        !output.status.success(),
        "expected a failure, got: {}",
        String::from_utf8_lossy(&output.stdout)
    );
    assert_eq!(output.status.code(), Some(1), "{stderr}");
    assert!(!stderr.contains("panicked"), "{stderr}");
    assert!(stderr.contains("uavmeta: "), "{stderr}");
    stderr
}

fn collect(
    dir: &Path,
    overrides: &[&str],
    task: &str,
    policy: &str,
    seed: u64,
    out: &str,
) -> String {
    let seed = seed.to_string();
    stdout(&uavmeta(
        dir,
        "collect",
        overrides,
        &[
            "--task", task, "--policy", policy, "--seed", &seed, "--out", out,
        ],
    ))
}

/// `lambda-300`'s dataset from an online agent (seed 1), the data the train tests learn from.
fn agent_data(dir: &Path) -> &'static str {
    let data = "data/lambda-300.uavds";
    collect(dir, SMALL, "lambda-300", "dqn-online", 1, data);
    data
}

/// `uavmeta train --algo cql` on `lambda-300`: SHOTS shots of DATASET for EPOCHS epochs into
/// OUT, then EXTRA.
fn train_cql(
    dir: &Path,
    dataset: &str,
    shots: &str,
    epochs: &str,
    out: &str,
    extra: &[&str],
) -> Output {
    let mut args = vec![
        "--task",
        "lambda-300",
        "--algo",
        "cql",
        "--dataset",
        dataset,
        "--shots",
        shots,
        "--epochs",
        epochs,
        "--out",
        out,
    ];
    args.extend_from_slice(extra);
    uavmeta(dir, "train", SMALL, &args)
}

fn read(dir: &Path, file: &str) -> Vec<u8> {
    let path: PathBuf = dir.join(file);
    std::fs::read(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

/// The header and the rows of a CSV file, each split at commas.
fn csv(dir: &Path, file: &str) -> (String, Vec<Vec<String>>) {
    let text = String::from_utf8(read(dir, file)).expect("utf-8 CSV");
    let mut lines = text.lines();
    let header = lines.next().expect("a header line").to_string();
    let rows = lines
        .map(|l| l.split(',').map(str::to_string).collect())
        .collect();
    (header, rows)
}

fn number(field: &str) -> f64 {
    field
        .parse()
        .unwrap_or_else(|e| panic!("`{field}` is not a number: {e}"))
}

#[test]
fn collect_is_reproducible_from_its_seed_and_from_its_saved_config() {
    let dir = tempfile::tempdir().expect("temp dir");
    for policy in ["stalest", "random", "dqn-online"] {
        let first = format!("{policy}/a.uavds");
        let text = collect(dir.path(), SMALL, "lambda-300", policy, 3, &first);
        assert!(
            text.contains(&format!(
                "120 transitions of task `lambda-300` by `{policy}` (seed 3"
            )),
            "{text}"
        );
        let second = format!("{policy}/b.uavds");
        collect(dir.path(), SMALL, "lambda-300", policy, 3, &second);
        let dataset = read(dir.path(), &first);
        assert!(
            dataset.len() > 120 * 20,
            "{policy}: {} bytes",
            dataset.len()
        );
        assert_eq!(
            dataset,
            read(dir.path(), &second),
            "{policy}: same seed, same bytes"
        );
        let saved = read(dir.path(), &format!("{first}.config.toml"));
        assert_eq!(
            saved,
            read(dir.path(), &format!("{second}.config.toml")),
            "{policy}: same config"
        );
        let saved = String::from_utf8(saved).expect("utf-8 config");
        assert!(saved.contains(&format!("policy = \"{policy}\"")), "{saved}");

        let other = format!("{policy}/seed-4.uavds");
        collect(dir.path(), SMALL, "lambda-300", policy, 4, &other);
        assert_ne!(
            dataset,
            read(dir.path(), &other),
            "{policy}: the seed is used"
        );

        // The saved config alone, with no flags, makes the same file again.
        let again = format!("{policy}/again.uavds");
        let saved_path = dir.path().join(format!("{first}.config.toml"));
        let output = Command::new(env!("CARGO_BIN_EXE_uavmeta"))
            .current_dir(dir.path())
            .arg("collect")
            .arg("--config")
            .arg(&saved_path)
            .args(["--task", "lambda-300", "--out", &again])
            .output()
            .expect("run uavmeta");
        stdout(&output);
        assert_eq!(
            dataset,
            read(dir.path(), &again),
            "{policy}: from the saved config"
        );
    }
}

#[test]
fn train_writes_a_row_per_epoch_and_a_checkpoint_that_eval_scores() {
    let dir = tempfile::tempdir().expect("temp dir");
    let d = dir.path();
    let data = agent_data(d);
    let text = stdout(&train_cql(d, data, "100", "3", "runs/cql", &[]));
    assert!(
        text.contains("cql on 100 shots of `lambda-300`, epoch 3"),
        "{text}"
    );
    for file in ["final.safetensors", "final.json", "final.toml"] {
        assert!(d.join("runs/cql").join(file).is_file(), "{file} is missing");
    }

    let (header, rows) = csv(d, "runs/cql/train.csv");
    assert_eq!(header, TRAIN_COLUMNS);
    assert_eq!(rows.len(), 3, "one row per epoch");
    for (i, row) in rows.iter().enumerate() {
        assert_eq!(row.len(), TRAIN_COLUMNS.split(',').count(), "{row:?}");
        assert_eq!(row[0], (i + 1).to_string(), "epoch");
        // One pass over 100 shots in minibatches of 64 is 2 gradient steps.
        assert_eq!(row[1], (2 * (i + 1)).to_string(), "steps so far");
        // The world is deterministic given the start cell: one episode from each of the 100
        // (learner.eval_episodes counts only where rain moves).
        assert_eq!(row[13], "100", "an exact evaluation's episodes");
        // Every column is a number, and each row scores its own epoch's network.
        assert_eq!(row[15], (i + 1).to_string(), "network_epoch");
        for field in row {
            assert!(number(field).is_finite(), "{row:?}");
        }
        assert!(
            number(&row[3]) >= 0.0,
            "the conservative term of eq. 8 is never negative"
        );
        assert!(number(&row[5]) < 0.0, "every reward is a cost");
    }

    // eval with the config's episodes and seed scores the final network as training's last
    // evaluation did.
    let text = stdout(&uavmeta(
        d,
        "eval",
        SMALL,
        &["--task", "lambda-300", "--checkpoint", "runs/cql/final"],
    ));
    let last = &rows[2];
    let lines: Vec<&str> = text.lines().collect();
    assert!(
        lines[0].starts_with(
            "runs/cql/final (cql, epoch 3) on `lambda-300`, 100 episodes seeded 12345"
        ),
        "{text}"
    );
    let expected = format!(
        "return    {:.1} ± {:.1}",
        number(&last[5]),
        number(&last[6])
    );
    assert_eq!(lines[1].trim(), expected, "{text}");
    for metric in ["AoI", "power mW", "outages"] {
        assert!(
            lines.iter().any(|l| l.trim_start().starts_with(metric)),
            "{text}"
        );
    }

    // A world of another size cannot use the network.
    let mut other_world = SMALL.to_vec();
    other_world.push("world.devices=5");
    let stderr = failure(&uavmeta(
        d,
        "eval",
        &other_world,
        &["--task", "lambda-300", "--checkpoint", "runs/cql/final"],
    ));
    assert!(stderr.contains("runs/cql/final.json"), "{stderr}");
    assert!(stderr.contains("input size (2 + K) 12"), "{stderr}");
    assert!(stderr.contains("gives 7 (world.devices)"), "{stderr}");
}

#[test]
fn train_init_seed_draws_the_random_init_apart_from_the_shots() {
    let dir = tempfile::tempdir().expect("temp dir");
    let d = dir.path();
    let data = agent_data(d);
    let train = |out: &str, seeds: &[&str]| train_cql(d, data, "50", "1", out, seeds);
    let weights = |out: &str| read(d, &format!("{out}/final.safetensors"));
    for (out, seeds) in [
        ("runs/s5", &["--seed", "5"][..]),
        ("runs/s5-i5", &["--seed", "5", "--init-seed", "5"]),
        ("runs/s5-i6", &["--seed", "5", "--init-seed", "6"]),
        ("runs/s6", &["--seed", "6"]),
    ] {
        stdout(&train(out, seeds));
    }
    assert_eq!(
        weights("runs/s5"),
        weights("runs/s5-i5"),
        "--init-seed defaults to --seed"
    );
    // Another init on the same shots and order: unlike both the run it varies and the run whose
    // init it takes.
    assert_ne!(weights("runs/s5-i6"), weights("runs/s5"));
    assert_ne!(weights("runs/s5-i6"), weights("runs/s6"));

    let stderr = failure(&train(
        "runs/refused",
        &["--init", "runs/s5/final", "--init-seed", "3"],
    ));
    assert!(stderr.contains("--init-seed"), "{stderr}");
    assert!(stderr.contains("`runs/s5/final`"), "{stderr}");
    assert!(!d.join("runs/refused").exists(), "{stderr}");
}

/// Random data of the two meta-train tasks and of lambda-300 in `dir/data`, and the overrides
/// that meta-train on the two, followed by `more`.
fn meta_data<'a>(dir: &Path, more: &[&'a str]) -> Vec<&'a str> {
    for task in ["lambda-0", "lambda-100", "lambda-300"] {
        collect(dir, SMALL, task, "random", 1, &format!("data/{task}.uavds"));
    }
    [SMALL, TWO_META_TRAIN_TASKS, more].concat()
}

/// The context learner as a user runs it: `meta-train --learner context` writes `OUT/context`
/// and each meta-train task's zero-shot return; `meta-test` reads the unseen task's code from its
/// shots, prints that policy's zero-shot return, fine-tunes it with CQL, and the same command
/// gives the same network to the byte.
#[test]
fn meta_train_writes_a_context_model_that_meta_test_reads_and_fine_tunes() {
    let dir = tempfile::tempdir().expect("temp dir");
    let d = dir.path();
    let meta = meta_data(d, &["meta.meta_epochs=4", "context.encoder_steps=20"]);
    let out = [
        "--datasets",
        "data",
        "--out",
        "runs/context",
        "--learner",
        "context",
    ];
    let text = stdout(&uavmeta(d, "meta-train", &meta, &out));
    assert!(text.contains("lambda-100: zero-shot return -"), "{text}");
    assert!(
        text.contains("context model: runs/context/context"),
        "{text}"
    );
    let model = String::from_utf8(read(d, "runs/context/context.json")).expect("utf-8");
    assert!(model.contains("cql-context"), "{model}");

    let test = |out: &str| {
        stdout(&uavmeta(
            d,
            "meta-test",
            &meta,
            &[
                "--task",
                "lambda-300",
                "--init",
                "runs/context/context",
                "--dataset",
                "data/lambda-300.uavds",
                "--shots",
                "64",
                "--epochs",
                "2",
                "--out",
                out,
            ],
        ))
    };
    let text = test("runs/test-a");
    assert!(text.contains("init, zero-shot: return -"), "{text}");
    assert!(
        text.contains("\nepoch 2") && text.contains(": return "),
        "{text}"
    );
    test("runs/test-b");
    assert!(
        read(d, "runs/test-a/final.safetensors") == read(d, "runs/test-b/final.safetensors"),
        "the same meta-test gave another network"
    );

    // The model's Q-network reads a task code after the observation: as a plain policy it is
    // refused, saying what it is and where it is used.
    let mut rollout = Command::new(env!("CARGO_BIN_EXE_uavmeta"));
    rollout
        .current_dir(d)
        .args(["env", "rollout", "--config", CONFIG]);
    for set in &meta {
        rollout.args(["--set", set]);
    }
    rollout.args([
        "--task",
        "lambda-300",
        "--policy",
        "q:0:runs/context/context",
    ]);
    let stderr = failure(&rollout.output().expect("run uavmeta"));
    assert!(
        stderr.contains("runs/context/context.json: a context learner's model (`cql-context`)"),
        "{stderr}"
    );
}

#[test]
fn meta_train_writes_w0_that_meta_test_fine_tunes() {
    let dir = tempfile::tempdir().expect("temp dir");
    let d = dir.path();
    let meta = meta_data(
        d,
        &[
            "meta.meta_epochs=4",
            "meta.support_batch_size=16",
            "meta.query_batch_size=16",
            "meta.eval_every=2",
            "meta.checkpoint_every=2",
        ],
    );
    let text = stdout(&uavmeta(
        d,
        "meta-train",
        &meta,
        &["--datasets", "data", "--out", "runs/maml"],
    ));
    assert!(text.contains("meta-epoch 4: meta-loss "), "{text}");
    assert!(text.contains("w0: runs/maml/w0;"), "{text}");

    let (header, rows) = csv(d, "runs/maml/meta_train.csv");
    assert_eq!(
        header,
        "meta_epoch,meta_loss,loss_lambda-0,loss_lambda-100,return_lambda-0,return_lambda-100,\
         zero_shot_lambda-0,zero_shot_lambda-100,seconds"
    );
    assert_eq!(rows.len(), 4, "one row per meta-epoch");
    for (i, row) in rows.iter().enumerate() {
        let epoch = i + 1;
        assert_eq!(row[0], epoch.to_string());
        // Every task is sampled each meta-epoch, so the meta-loss (eq. 15) is their sum.
        let losses = number(&row[2]) + number(&row[3]);
        assert!(
            (number(&row[1]) - losses).abs() < 1e-9 * losses.abs().max(1.0),
            "{row:?}"
        );
        let evaluated = epoch % 2 == 0;
        for ret in &row[4..8] {
            assert_eq!(!ret.is_empty(), evaluated, "meta-epoch {epoch}: {row:?}");
            if evaluated {
                assert!(number(ret) < 0.0, "{row:?}");
            }
        }
    }
    let checkpoints = ["w0-e0002", "w0"];
    for name in checkpoints {
        for ext in ["safetensors", "json", "toml"] {
            assert!(
                d.join(format!("runs/maml/{name}.{ext}")).is_file(),
                "{name}.{ext}"
            );
        }
    }
    assert!(
        !d.join("runs/maml/w0-e0001.json").exists(),
        "checkpoint_every = 2"
    );
    let w0 = String::from_utf8(read(d, "runs/maml/w0.json")).expect("utf-8 metadata");
    assert!(w0.contains("cql-maml"), "{w0}");

    // As if killed after meta-epoch 3: the last checkpoint on disk is meta-epoch 2's. `--resume`
    // continues from it, with its optimiser state, to the uninterrupted run's w0 and log.
    let weights = read(d, "runs/maml/w0.safetensors");
    let without_seconds = |rows: Vec<Vec<String>>| -> Vec<Vec<String>> {
        rows.into_iter()
            .map(|r| r[..r.len() - 1].to_vec())
            .collect()
    };
    let log = without_seconds(rows);
    for ext in [
        "safetensors",
        "json",
        "toml",
        "state.json",
        "state.safetensors",
    ] {
        std::fs::remove_file(d.join(format!("runs/maml/w0.{ext}"))).expect("remove the last w0");
    }
    let (_, rows) = csv(d, "runs/maml/meta_train.csv");
    std::fs::write(
        d.join("runs/maml/meta_train.csv"),
        format!(
            "{header}\n{}\n",
            rows[..3]
                .iter()
                .map(|r| r.join(","))
                .collect::<Vec<_>>()
                .join("\n")
        ),
    )
    .expect("cut the log after meta-epoch 3");
    let resume = ["--datasets", "data", "--out", "runs/maml", "--resume"];
    stdout(&uavmeta(d, "meta-train", &meta, &resume));
    assert!(
        read(d, "runs/maml/w0.safetensors") == weights,
        "the resumed w0 differs"
    );
    let (_, rows) = csv(d, "runs/maml/meta_train.csv");
    assert_eq!(without_seconds(rows), log);

    // Averaging the evaluation over three adaptations changes the adapted returns, not the
    // training nor w0's zero-shot returns.
    let averaged: Vec<&str> = meta
        .iter()
        .copied()
        .chain(["meta.eval_adaptations=3"])
        .collect();
    let out = ["--datasets", "data", "--out", "runs/maml-averaged"];
    stdout(&uavmeta(d, "meta-train", &averaged, &out));
    assert!(
        read(d, "runs/maml-averaged/w0.safetensors") == weights,
        "evaluating changed w0"
    );
    let (_, averaged_rows) = csv(d, "runs/maml-averaged/meta_train.csv");
    let averaged_log = without_seconds(averaged_rows);
    for (one, three) in log.iter().zip(&averaged_log) {
        assert_eq!(one[..4], three[..4], "meta-losses");
        assert_eq!(one[6..8], three[6..8], "zero-shot returns");
    }
    assert!(
        log.iter()
            .zip(&averaged_log)
            .any(|(one, three)| one[4..6] != three[4..6]),
        "three adaptations scored exactly as one: {averaged_log:?}"
    );

    let text = stdout(&uavmeta(
        d,
        "meta-test",
        SMALL,
        &[
            "--task",
            "lambda-300",
            "--init",
            "runs/maml/w0",
            "--dataset",
            "data/lambda-300.uavds",
            "--shots",
            "64",
            "--epochs",
            "3",
            "--out",
            "runs/test",
        ],
    ));
    assert!(
        text.contains("\nepoch 3") && text.contains(": return "),
        "{text}"
    );
    let (header, rows) = csv(d, "runs/test/train.csv");
    assert_eq!(header, TRAIN_COLUMNS);
    let epochs: Vec<&str> = rows.iter().map(|r| r[0].as_str()).collect();
    assert_eq!(epochs, ["1", "2", "3"]);
    assert!(d.join("runs/test/final.safetensors").is_file());

    // meta-test starts only from a meta-trained w0.
    stdout(&train_cql(
        d,
        "data/lambda-300.uavds",
        "64",
        "1",
        "runs/cql",
        &[],
    ));
    let stderr = failure(&uavmeta(
        d,
        "meta-test",
        SMALL,
        &[
            "--task",
            "lambda-300",
            "--init",
            "runs/cql/final",
            "--dataset",
            "data/lambda-300.uavds",
            "--shots",
            "64",
            "--out",
            "runs/bad",
        ],
    ));
    assert!(
        stderr.contains("runs/cql/final: trained by `cql`"),
        "{stderr}"
    );

    // Without the overrides the config meta-trains on eight tasks: the first missing file is named.
    let stderr = failure(&uavmeta(
        d,
        "meta-train",
        SMALL,
        &["--datasets", "data", "--out", "runs/eight"],
    ));
    assert!(
        stderr.contains("data/lambda-200.uavds: cannot read"),
        "{stderr}"
    );
}

#[test]
fn a_damaged_dataset_is_refused_naming_the_file_and_the_offset() {
    let dir = tempfile::tempdir().expect("temp dir");
    let d = dir.path();
    collect(d, SMALL, "lambda-300", "stalest", 2, "good.uavds");
    let good = read(d, "good.uavds");
    let train = |dataset: &str| {
        let out = format!("runs/{dataset}");
        let output = train_cql(d, dataset, "10", "1", &out, &[]);
        let stderr = failure(&output);
        assert!(
            !d.join(&out).exists(),
            "a refused run leaves no output: {stderr}"
        );
        stderr
    };

    std::fs::write(d.join("cut.uavds"), &good[..good.len() - 7]).expect("write");
    let stderr = train("cut.uavds");
    assert!(stderr.contains("uavmeta: cut.uavds: offset "), "{stderr}");
    assert!(stderr.contains("cut short"), "{stderr}");

    let mut flipped = good.clone();
    flipped[good.len() / 2] ^= 0x40;
    std::fs::write(d.join("flipped.uavds"), &flipped).expect("write");
    let stderr = train("flipped.uavds");
    assert!(
        stderr.contains("uavmeta: flipped.uavds: offset "),
        "{stderr}"
    );
    assert!(stderr.contains("CRC32"), "{stderr}");

    std::fs::write(d.join("header.uavds"), &good[..20]).expect("write");
    let stderr = train("header.uavds");
    assert!(
        stderr.contains("uavmeta: header.uavds: offset 20: "),
        "{stderr}"
    );

    std::fs::write(d.join("other.uavds"), b"not a dataset at all").expect("write");
    let stderr = train("other.uavds");
    assert!(
        stderr.contains("other.uavds: not a uavmeta dataset"),
        "{stderr}"
    );
}

#[test]
fn an_unknown_config_key_is_refused_naming_the_file_and_the_key() {
    let dir = tempfile::tempdir().expect("temp dir");
    let d = dir.path();
    collect(d, SMALL, "lambda-300", "random", 0, "data.uavds");
    let train_args = [
        "--task",
        "lambda-300",
        "--algo",
        "cql",
        "--dataset",
        "data.uavds",
        "--shots",
        "10",
        "--out",
        "runs/x",
    ];

    std::fs::write(d.join("typo.toml"), "[learner]\nepochz = 3\n").expect("write config");
    let output = Command::new(env!("CARGO_BIN_EXE_uavmeta"))
        .current_dir(d)
        .args(["train", "--config", "typo.toml"])
        .args(train_args)
        .output()
        .expect("run uavmeta");
    let stderr = failure(&output);
    assert!(stderr.contains("uavmeta: typo.toml: "), "{stderr}");
    assert!(stderr.contains("unknown field `epochz`"), "{stderr}");

    let mut overrides = SMALL.to_vec();
    overrides.push("collect.polcy=random");
    let stderr = failure(&uavmeta(d, "train", &overrides, &train_args));
    assert!(stderr.contains(CONFIG), "{stderr}");
    assert!(stderr.contains("--set collect.polcy=random"), "{stderr}");
    assert!(stderr.contains("unknown field `polcy`"), "{stderr}");
    assert!(!d.join("runs/x").exists());
}
