//! End-to-end tests of the multi-process runtime: the real `uavmeta` binary, as separate
//! processes talking over iceoryx2, scraped over HTTP.
//!
//! Every test runs in its own temporary run directory (so its iceoryx2 services are its own),
//! on a small config, and kills what it started when it ends, even on failure.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use uavmeta_proto::method::{Algo, Method};
use uavmeta_proto::metrics::{self, Metric};
use uavmeta_runtime::metrics::{parse, sum, Sample};

mod support;
use support::{
    child_pid, child_pids, config_args, dataset_seqs, launch, missing_tool, run_dir, table_return,
    wait_until, within, Finished, Proc, BIN,
};

fn stderr(finished: &Finished) -> String {
    finished.stderr.clone()
}

/// The samples of a process's final metrics snapshot, checked by promtool when installed.
fn snapshot(run: &Path, process: &str) -> Vec<Sample> {
    let path = run.join("metrics").join(format!("{process}.prom"));
    let text = std::fs::read_to_string(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    promtool_check(&text, &path.display().to_string());
    parse(&text).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

/// `promtool check metrics` on `text`, when promtool is installed (Debian: `prometheus`); under
/// `CI=true` it must be (`make test` installs it).
fn promtool_check(text: &str, what: &str) {
    use std::io::Write;
    let spawned = Command::new("promtool")
        .args(["check", "metrics"])
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn();
    let mut child = match spawned {
        Ok(child) => child,
        Err(e) => {
            missing_tool(&format!("promtool (to check {what})"), &e);
            return;
        }
    };
    child
        .stdin
        .take()
        .expect("stdin")
        .write_all(text.as_bytes())
        .expect("write to promtool");
    let out = child.wait_with_output().expect("promtool");
    assert!(
        out.status.success(),
        "promtool check metrics {what}:\n{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
}

/// Scrapes a live process over HTTP, via the port it wrote, and parses (and lints) the answer.
fn scrape(run: &Path, process: &str) -> Vec<Sample> {
    let port_file = run.join("ports").join(format!("{process}.port"));
    let start = Instant::now();
    let port: u16 = loop {
        if let Some(port) = std::fs::read_to_string(&port_file)
            .ok()
            .and_then(|p| p.trim().parse().ok())
        {
            break port;
        }
        assert!(
            start.elapsed() < within(60),
            "{} never appeared",
            port_file.display()
        );
        std::thread::sleep(Duration::from_millis(50));
    };
    let text = uavmeta_runtime::metrics::scrape("127.0.0.1", port)
        .unwrap_or_else(|e| panic!("{process}: {e}"));
    promtool_check(&text, process);
    parse(&text).unwrap_or_else(|e| panic!("{process}: {e}"))
}

/// Transitions missing from a file: below each actor's highest stored number, not stored.
fn missing_in_files(seqs: &BTreeMap<u32, Vec<u64>>) -> u64 {
    seqs.values()
        .map(|s| s.last().map_or(0, |last| last + 1) - s.len() as u64)
        .sum()
}

/// `metric` summed over the final metrics of every actor of the run.
fn actors_total(run: &Path, metric: Metric) -> f64 {
    actor_names(run)
        .iter()
        .map(|a| sum(&snapshot(run, a), metric, &[]))
        .sum()
}

/// The actors that wrote a final metrics snapshot.
fn actor_names(run: &Path) -> Vec<String> {
    actor_files(&run.join("metrics"), "prom")
}

/// The actors named by the files of extension `extension` in `dir`. Files being written
/// atomically (`run_dir::write_atomic`'s `<name>.tmp.<pid>`) have another extension, so a name
/// is only taken once its file is complete.
fn actor_files(dir: &Path, extension: &str) -> Vec<String> {
    std::fs::read_dir(dir)
        .map(|d| {
            d.filter_map(|e| {
                let path = e.ok()?.path();
                if path.extension()? != extension {
                    return None;
                }
                path.file_stem()?.to_str().map(str::to_string)
            })
            .filter(|n| n.starts_with("actor-"))
            .collect()
        })
        .unwrap_or_default()
}

#[test]
fn a_small_launch_accounts_for_every_transition_and_its_rows_rerun_from_the_cli() {
    let dir = run_dir("e2e-launch-");
    let run = dir.path().join("run");
    let out = launch(dir.path(), &run, &[]).wait(within(240));
    assert!(out.status.success(), "launch failed:\n{}", stderr(&out));
    let table = out.stdout.clone();
    for method in [
        "maml-init",
        "context-init",
        "cql-maml",
        "cql-context",
        "cql",
    ] {
        assert!(
            table
                .lines()
                .any(|l| l.starts_with("lambda-300") && l.contains(method)),
            "no {method} row in:\n{table}"
        );
    }

    let store = snapshot(&run, "store");
    let published = actors_total(&run, metrics::actor::TRANSITIONS_PUBLISHED);
    let resent = actors_total(&run, metrics::actor::TRANSITIONS_RESENT);
    let stored = sum(&store, metrics::store::TRANSITIONS_STORED, &[]);
    let dropped = sum(&store, metrics::store::TRANSITIONS_DROPPED, &[]);
    let missing = sum(&store, metrics::store::TRANSITIONS_MISSING, &[]);
    assert!(published >= 3.0 * 300.0, "published {published}");
    assert_eq!(
        published + resent,
        stored + dropped,
        "published + resent = stored + dropped"
    );
    assert_eq!(missing, 0.0);
    assert_eq!(
        sum(
            &store,
            metrics::store::TRANSITIONS_DROPPED,
            &[("reason", metrics::store::FOREIGN)]
        ),
        0.0
    );
    let seqs = dataset_seqs(&run);
    assert_eq!(seqs.len(), 3);
    for (task, per_actor) in &seqs {
        assert_eq!(
            per_actor.values().map(Vec::len).sum::<usize>(),
            300,
            "{task}"
        );
        assert_eq!(missing_in_files(per_actor), 0, "{task}");
    }
    for process in ["launcher", "meta-learner", "evaluator"] {
        snapshot(&run, process);
    }
    let evaluator = snapshot(&run, "evaluator");
    assert!(sum(&evaluator, metrics::evaluator::CHECKPOINTS_EVALUATED, &[]) >= 2.0 + 2.0 * 2.0);
    assert!(run.join("prometheus.yml").exists());
    assert_rows_rerun_from_the_cli(dir.path(), &run);
}

/// The launch's `cql`, `cql-maml` and `cql-context` rows (seed 0, 300 shots: the whole dataset,
/// 2 epochs) re-run by hand as docs/TOUR.md says, `uavmeta train --init random --seed 0
/// --init-seed 1`, `uavmeta meta-test --init RUN/inits/w0 --seed 0` and `uavmeta meta-test
/// --init RUN/inits/cql-context --seed 0`, end on the launch's checkpoints byte for byte.
fn assert_rows_rerun_from_the_cli(dir: &Path, run: &Path) {
    let config = run.join("config.toml").display().to_string();
    let dataset = run.join("datasets/lambda-300.uavds").display().to_string();
    let w0 = run.join("inits/w0").display().to_string();
    let context = run.join("inits/cql-context").display().to_string();
    let cql = [
        "train",
        "--algo",
        "cql",
        "--init",
        "random",
        "--init-seed",
        "1",
    ];
    let cql_maml = ["meta-test", "--init", &w0];
    let cql_context = ["meta-test", "--init", &context];
    for (method, command) in [
        ("cql", &cql[..]),
        ("cql-maml", &cql_maml[..]),
        ("cql-context", &cql_context[..]),
    ] {
        let out = dir.join(format!("cli-{method}"));
        let rerun = Command::new(BIN)
            .args(command)
            .args([
                "--config",
                &config,
                "--task",
                "lambda-300",
                "--dataset",
                &dataset,
            ])
            .args(["--shots", "300", "--seed", "0", "--out"])
            .arg(&out)
            .output()
            .expect("run uavmeta");
        assert!(
            rerun.status.success(),
            "{method}: the CLI re-run failed: {}",
            String::from_utf8_lossy(&rerun.stderr)
        );
        let by_hand = std::fs::read(out.join("final.safetensors")).expect("the re-run's weights");
        let launched = run.join(format!(
            "checkpoints/{method}/lambda-300/epoch-00002.safetensors"
        ));
        let launched =
            std::fs::read(&launched).unwrap_or_else(|e| panic!("{}: {e}", launched.display()));
        assert!(
            by_hand == launched,
            "{method}: the CLI re-run is not the launch's checkpoint"
        );
    }
}

#[test]
fn a_launch_over_two_seeds_runs_each_in_its_own_directory_and_reports_their_mean() {
    let dir = run_dir("e2e-seeds-");
    let run = dir.path().join("run");
    let out = launch(dir.path(), &run, &["run.seeds=[0, 1]"]).wait(within(480));
    assert!(out.status.success(), "launch failed:\n{}", stderr(&out));
    let table = out.stdout.clone();
    let datasets: Vec<Vec<u8>> = [0, 1]
        .iter()
        .map(|s| {
            let seed_run = run.join(format!("seed-{s}"));
            assert!(
                seed_run.join("evaluations.csv").exists(),
                "{}",
                seed_run.display()
            );
            std::fs::read(seed_run.join("datasets/lambda-300.uavds")).expect("seed's dataset")
        })
        .collect();
    assert_ne!(
        datasets[0], datasets[1],
        "the seeds' actors share randomness"
    );
    for method in ["cql", "cql-maml", "maml-init"] {
        let (a, b) = (
            table_return(&table, "seed 0:", method),
            table_return(&table, "seed 1:", method),
        );
        let mean = table_return(&table, "over seeds [0, 1]", method);
        assert!(
            (mean - (a + b) / 2.0).abs() < 0.1,
            "{method}: {mean} is not the mean of {a} and {b}:\n{table}"
        );
    }
}

/// A store started by hand on a new run of the small config with `overrides`, once it serves.
fn start_store(dir: &Path, run: &Path, overrides: &[&str]) -> Proc {
    let mut args = vec![
        "store".to_string(),
        "--run".into(),
        run.display().to_string(),
    ];
    args.extend(config_args(dir, run, overrides));
    let store = Proc::spawn("store", &args);
    wait_until("the store", within(60), || {
        run.join("ports/store.port").exists()
    });
    store
}

/// An actor started by hand on `run`'s `task`, with `extra` arguments.
fn start_actor(run: &Path, task: &str, extra: &[&str]) -> Proc {
    let mut args = vec![
        "actor".to_string(),
        "--run".into(),
        run.display().to_string(),
        "--task".into(),
        task.into(),
    ];
    args.extend(extra.iter().map(|a| a.to_string()));
    Proc::spawn("actor", &args)
}

#[test]
fn hand_started_actors_add_data_and_every_endpoint_is_scraped_live() {
    let dir = run_dir("e2e-hand-");
    let run = dir.path().join("run");
    let run_arg = run.display().to_string();
    let store = start_store(dir.path(), &run, &["collect.transitions=1000000"]);

    let first =
        start_actor(&run, "lambda-100", &["--seed", "1", "--transitions", "400"]).wait(within(60));
    assert!(first.status.success(), "{}", stderr(&first));
    wait_until("400 stored", within(30), || {
        sum(
            &scrape(&run, "store"),
            metrics::store::DATASET_TRANSITIONS,
            &[("task", "lambda-100")],
        ) == 400.0
    });

    // A second actor joins the running store, is scraped while it runs, and is stopped by hand.
    let second = start_actor(&run, "lambda-100", &["--seed", "2"]);
    let names = || actor_names_live(&run);
    wait_until("the second actor's port", within(60), || {
        !names().is_empty()
    });
    // Its own endpoint, scraped while it runs, shows it stepping.
    let live_actor = names()[0].clone();
    wait_until(
        "the second actor's steps on its /metrics",
        within(60),
        || {
            let live = scrape(&run, &live_actor);
            live.iter().any(|s| s.name == metrics::actor::STEPS.name)
                && sum(&live, metrics::actor::STEPS, &[]) > 0.0
        },
    );
    wait_until("the second actor's data", within(30), || {
        sum(
            &scrape(&run, "store"),
            metrics::store::DATASET_TRANSITIONS,
            &[("task", "lambda-100")],
        ) > 400.0
    });
    second.signal(libc::SIGTERM);
    let second = second.wait(within(30));
    assert!(
        second.status.success(),
        "a stopped actor exits cleanly:\n{}",
        stderr(&second)
    );

    // The meta-learner and the evaluator serve /metrics while they wait.
    let learner = Proc::spawn(
        "meta-learner",
        &["meta-learner".to_string(), "--run".into(), run_arg.clone()],
    );
    let evaluator = Proc::spawn(
        "evaluator",
        &["evaluator".to_string(), "--run".into(), run_arg.clone()],
    );
    assert_eq!(
        sum(
            &scrape(&run, "meta-learner"),
            metrics::meta_learner::META_EPOCH,
            &[]
        ),
        0.0
    );
    assert_eq!(
        sum(
            &scrape(&run, "evaluator"),
            metrics::evaluator::CHECKPOINTS_EVALUATED,
            &[]
        ),
        0.0
    );
    for p in [&learner, &evaluator, &store] {
        p.signal(libc::SIGTERM);
    }
    for p in [learner, evaluator, store] {
        let name = p.name.clone();
        let out = p.wait(within(30));
        assert!(
            out.status.success(),
            "{name} exits cleanly on SIGTERM:\n{}",
            stderr(&out)
        );
    }

    let seqs = dataset_seqs(&run);
    let per_actor = &seqs["lambda-100"];
    assert_eq!(per_actor.len(), 2, "both actors' data is stored");
    assert!(per_actor
        .values()
        .all(|s| s[0] == 0 && missing_in_files(&BTreeMap::from([(0, s.clone())])) == 0));
    let store = snapshot(&run, "store");
    assert_eq!(
        actors_total(&run, metrics::actor::TRANSITIONS_PUBLISHED)
            + actors_total(&run, metrics::actor::TRANSITIONS_RESENT),
        sum(&store, metrics::store::TRANSITIONS_STORED, &[])
            + sum(&store, metrics::store::TRANSITIONS_DROPPED, &[])
    );
}

/// Actors whose port file exists: the running ones.
fn actor_names_live(run: &Path) -> Vec<String> {
    actor_files(&run.join("ports"), "port")
}

fn kill9(pid: i32) {
    // SAFETY: a signal to a process this test's launcher started.
    unsafe { libc::kill(pid, libc::SIGKILL) };
}

/// The paper's behaviour policy publishes a fixed replay sample once. If the store dies holding
/// part of it unwritten, nothing else will ever send those transitions, so the actor must send its
/// sample again to the store that replaces the dead one, or the dataset never completes.
#[test]
fn a_replay_sample_lost_with_a_killed_store_is_sent_again_to_its_successor() {
    let dir = run_dir("e2e-resend-");
    let run = dir.path().join("run");
    let run_arg = run.display().to_string();
    let first = start_store(
        dir.path(),
        &run,
        &[
            "collect.policy=dqn-online",
            "collect.dqn.steps=600",
            "collect.dqn.learning_starts=100",
            "collect.dqn.eps_decay_steps=300",
            "collect.transitions=300",
        ],
    );
    // Stopped, the store takes batches into its queue but never writes them.
    first.signal(libc::SIGSTOP);
    let actor = start_actor(&run, "lambda-0", &[]);
    wait_until("the sample sent", within(120), || {
        actor_names_live(&run).first().is_some_and(|name| {
            sum(
                &scrape(&run, name),
                metrics::actor::TRANSITIONS_PUBLISHED,
                &[],
            ) == 300.0
        })
    });
    first.signal(libc::SIGKILL);
    let killed = first.wait(within(30));
    assert!(!killed.status.success());
    assert!(
        dataset_seqs(&run)
            .get("lambda-0")
            .is_none_or(BTreeMap::is_empty),
        "the stopped store wrote part of the sample"
    );

    let second = Proc::spawn("store", &["store".into(), "--run".into(), run_arg.clone()]);
    // The actor ends by itself once its task's dataset is announced complete.
    let actor = actor.wait(within(60));
    assert!(actor.status.success(), "{}", stderr(&actor));
    let seqs = dataset_seqs(&run);
    let per_actor = &seqs["lambda-0"];
    assert_eq!(per_actor.len(), 1, "{per_actor:?}");
    let stored = per_actor.values().next().expect("the actor's transitions");
    assert_eq!(*stored, (0..300).collect::<Vec<u64>>());
    second.signal(libc::SIGTERM);
    let second = second.wait(within(30));
    assert!(second.status.success(), "{}", stderr(&second));
    let store = snapshot(&run, "store");
    assert_eq!(
        sum(
            &store,
            metrics::store::TRANSITIONS_MISSING,
            &[("task", "lambda-0")]
        ),
        0.0
    );
    let actor_metrics = snapshot(&run, &actor_names(&run)[0]);
    assert!(
        sum(&actor_metrics, metrics::actor::STORE_CHANGES, &[]) >= 1.0,
        "the resend is counted"
    );
}

/// An online DQN actor on a task whose dataset is already complete (a resumed launch, another
/// actor's data) stops training once it hears so, instead of training its whole budget for
/// transitions the store no longer takes. The budget here is far beyond the wait.
#[test]
fn an_online_dqn_actor_stops_training_once_its_dataset_is_complete() {
    let dir = run_dir("e2e-complete-");
    let run = dir.path().join("run");
    let store = start_store(
        dir.path(),
        &run,
        &[
            "collect.policy=dqn-online",
            "collect.dqn.steps=10000000",
            "collect.transitions=300",
        ],
    );
    let random = start_actor(&run, "lambda-0", &["--policy", "random"]).wait(within(120));
    assert!(random.status.success(), "{}", stderr(&random));
    let dqn = start_actor(&run, "lambda-0", &[]).wait(within(300));
    assert!(dqn.status.success(), "{}", stderr(&dqn));
    assert!(
        stderr(&dqn).contains("stopped while training the online DQN agent"),
        "{}",
        stderr(&dqn)
    );
    store.signal(libc::SIGTERM);
    let store = store.wait(within(30));
    assert!(store.status.success(), "{}", stderr(&store));
}

/// A rollout cannot be replayed, so an actor keeps every batch until the store acknowledges it
/// appended it: batches a killed store held unwritten go to its successor, nothing is missing,
/// and the actor ends only once its last transition is stored.
#[test]
fn a_rollout_held_by_a_killed_store_is_sent_again_to_its_successor() {
    let dir = run_dir("e2e-rollout-resend-");
    let run = dir.path().join("run");
    let run_arg = run.display().to_string();
    let first = start_store(dir.path(), &run, &["collect.transitions=100000"]);
    // Stopped, the store takes batches into its queue (64 batches of 16) but never writes them.
    first.signal(libc::SIGSTOP);
    let sent = 800u64;
    let actor = start_actor(&run, "lambda-100", &["--transitions", &sent.to_string()]);
    let live = |metric: Metric| {
        actor_names_live(&run)
            .first()
            .map_or(0.0, |name| sum(&scrape(&run, name), metric, &[]))
    };
    wait_until("the rollout sent", within(120), || {
        live(metrics::actor::TRANSITIONS_PUBLISHED) == sent as f64
    });
    assert_eq!(
        live(metrics::actor::TRANSITIONS_UNACKNOWLEDGED),
        sent as f64,
        "the actor keeps what the stopped store has not acknowledged"
    );
    first.signal(libc::SIGKILL);
    let killed = first.wait(within(30));
    assert!(!killed.status.success());
    assert!(
        dataset_seqs(&run)
            .get("lambda-100")
            .is_none_or(BTreeMap::is_empty),
        "the stopped store wrote part of the rollout"
    );

    let second = Proc::spawn("store", &["store".into(), "--run".into(), run_arg.clone()]);
    // The actor ends by itself once the new store has acknowledged everything.
    let actor = actor.wait(within(60));
    assert!(actor.status.success(), "{}", stderr(&actor));
    let seqs = dataset_seqs(&run);
    let per_actor = &seqs["lambda-100"];
    assert_eq!(per_actor.len(), 1, "{per_actor:?}");
    let stored = per_actor.values().next().expect("the actor's transitions");
    assert_eq!(*stored, (0..sent).collect::<Vec<u64>>());
    second.signal(libc::SIGTERM);
    let second = second.wait(within(30));
    assert!(second.status.success(), "{}", stderr(&second));
    let store = snapshot(&run, "store");
    assert_eq!(sum(&store, metrics::store::TRANSITIONS_MISSING, &[]), 0.0);
    let actor_metrics = snapshot(&run, &actor_names(&run)[0]);
    for (metric, expected) in [
        (metrics::actor::TRANSITIONS_PUBLISHED, sent as f64),
        (metrics::actor::TRANSITIONS_RESENT, sent as f64),
        (metrics::actor::TRANSITIONS_UNACKNOWLEDGED, 0.0),
    ] {
        assert_eq!(
            sum(&actor_metrics, metric, &[]),
            expected,
            "{}",
            metric.name
        );
    }
    assert!(sum(&actor_metrics, metrics::actor::STORE_CHANGES, &[]) >= 1.0);
}

/// Meta-training long enough (one outer step per meta-epoch, a checkpoint every 100) for a test to
/// kill or stop the meta-learner mid-way, whatever the machine's speed; the fine-tuning after it
/// on the small run's 300 shots, not on these tests' datasets of hundreds of thousands (two
/// thirds of a launch's time, and nothing a kill lands in).
const LONG_META_TRAINING: [&str; 4] = [
    "meta.meta_epochs=3000",
    "meta.outer_steps_per_meta_epoch=1",
    "meta.checkpoint_every=100",
    "learner.shots=300",
];

#[test]
fn killed_actor_store_and_meta_learner_are_restarted_and_nothing_is_lost_unaccounted() {
    let dir = run_dir("e2e-kill-");
    let run = dir.path().join("run");
    let run_arg = run.display().to_string();
    // Long enough to be killed in the middle of each phase.
    let launcher = launch(
        dir.path(),
        &run,
        // One outer step per meta-epoch: a pass over 300 000 support shots would be 18 750.
        &[&["collect.transitions=600000"][..], &LONG_META_TRAINING].concat(),
    );

    // The store, mid-collection.
    let mut held = 0.0;
    wait_until("collection under way", within(60), || {
        held = match run.join("ports/store.port").exists() {
            true => sum(
                &scrape(&run, "store"),
                metrics::store::DATASET_TRANSITIONS,
                &[],
            ),
            false => 0.0,
        };
        held > 100_000.0
    });
    kill9(child_pid(&[" store ", &run_arg]).expect("the store's pid"));
    assert!(
        held < 3.0 * 600_000.0,
        "the store was killed after collection ended"
    );
    // An actor, mid-collection (after the store came back).
    wait_until("the store restarted", within(60), || {
        run.join("ports/store.port").exists()
    });
    if let Some(pid) = child_pid(&[" actor ", &run_arg, "lambda-0"]) {
        kill9(pid);
    }
    // The meta-learner, mid-training, once it has written a checkpoint.
    wait_until("a w0 checkpoint", within(180), || {
        run.join("checkpoints/maml-init/epoch-00200.json").exists()
    });
    kill9(child_pid(&[" meta-learner ", &run_arg]).expect("the meta-learner's pid"));
    assert!(
        !run.join("checkpoints/maml-init/epoch-03000.json").exists(),
        "the meta-learner was killed after meta-training"
    );

    let out = launcher.wait(within(300));
    assert!(out.status.success(), "launch failed:\n{}", stderr(&out));
    let launcher_metrics = snapshot(&run, "launcher");
    for process in ["store", "meta-learner"] {
        assert!(
            sum(
                &launcher_metrics,
                metrics::launcher::CHILD_RESTARTS,
                &[("process", process)]
            ) >= 1.0,
            "{process} was not restarted"
        );
    }
    let learner_log =
        std::fs::read_to_string(run.join("logs/meta-learner.log")).expect("meta-learner log");
    assert!(
        learner_log.contains("resuming meta-training"),
        "{learner_log}"
    );
    assert_every_transition_accounted(&run, 600_000);
    let table = out.stdout.clone();
    assert!(table.contains("cql-maml"), "{table}");
}

/// Every dataset file of a finished run reads back, holds `per_task` transitions, each once, and
/// lacks none: the store counted nothing missing, and the files agree.
fn assert_every_transition_accounted(run: &Path, per_task: usize) {
    let store = snapshot(run, "store");
    let seqs = dataset_seqs(run);
    for (task, per_actor) in &seqs {
        assert_eq!(
            per_actor.values().map(Vec::len).sum::<usize>(),
            per_task,
            "{task}"
        );
        let counted = sum(
            &store,
            metrics::store::TRANSITIONS_MISSING,
            &[("task", task)],
        );
        assert_eq!(
            missing_in_files(per_actor) as f64,
            counted,
            "{task}: missing transitions vs the store's count"
        );
        // Actors keep what a store has not acknowledged and send it to the store's successor.
        assert_eq!(counted, 0.0, "{task}: transitions lost with a killed store");
    }
}

/// The launcher's live count of children it killed as hung, over the processes named `prefix`*.
fn hangs(run: &Path, prefix: &str) -> f64 {
    scrape(run, "launcher")
        .iter()
        .filter(|s| s.name == metrics::launcher::CHILD_HANGS.name)
        .filter(|s| s.label("process").is_some_and(|p| p.starts_with(prefix)))
        .map(|s| s.value)
        .sum()
}

#[test]
fn stopped_actor_store_and_meta_learner_are_taken_for_hung_and_restarted() {
    let dir = run_dir("e2e-hang-");
    let run = dir.path().join("run");
    let run_arg = run.display().to_string();
    let launcher = launch(
        dir.path(),
        &run,
        &[
            &["run.hang_timeout_seconds=10", "collect.transitions=600000"][..],
            &LONG_META_TRAINING,
        ]
        .concat(),
    );
    // SIGSTOP: the process stays, holds its ports and answers nothing, as a deadlocked one would.
    let stop = |needles: &[&str], process: &str| {
        let pid = child_pid(needles).unwrap_or_else(|| panic!("no running {process}"));
        // SAFETY: a signal to a process this test's launcher started.
        unsafe { libc::kill(pid, libc::SIGSTOP) };
        wait_until(&format!("{process} killed as hung"), within(120), || {
            hangs(&run, process) >= 1.0
        });
    };
    wait_until("collection under way", within(60), || {
        run.join("ports/store.port").exists()
            && sum(
                &scrape(&run, "store"),
                metrics::store::DATASET_TRANSITIONS,
                &[],
            ) > 10_000.0
    });
    stop(&[" actor ", &run_arg, "lambda-0"], "actor-lambda-0");
    stop(&[" store ", &run_arg], "store");
    wait_until("a w0 checkpoint", within(180), || {
        run.join("checkpoints/maml-init/epoch-00200.json").exists()
    });
    stop(&[" meta-learner ", &run_arg], "meta-learner");

    let out = launcher.wait(within(300));
    assert!(out.status.success(), "launch failed:\n{}", stderr(&out));
    let launcher_metrics = snapshot(&run, "launcher");
    for process in ["store", "meta-learner"] {
        assert_eq!(
            sum(
                &launcher_metrics,
                metrics::launcher::CHILD_RESTARTS,
                &[("process", process)]
            ),
            1.0,
            "{process}: restarted once, after its hang\n{}",
            stderr(&out)
        );
    }
    assert_every_transition_accounted(&run, 600_000);
    assert!(out.stdout.contains("cql-maml"), "{}", out.stdout);
}

/// The children of the run `run_arg` that are alive now, by role (the subcommand).
fn live_children(run_arg: &str) -> Vec<(&'static str, i32)> {
    ["store", "actor", "meta-learner", "evaluator"]
        .into_iter()
        .filter_map(|role| Some((role, child_pid(&[&format!(" {role} "), run_arg])?)))
        .collect()
}

/// kill -9 on a seeded schedule: one actor mid-collection, then `kills - 1` random live children
/// (the store and the meta-learner among them), each once meta-training has passed a seeded w0
/// checkpoint, so every kill lands while the run is under way however fast or slow the machine.
/// The launcher restarts each; afterwards the run ends with its table and every transition is
/// stored exactly once.
fn chaos(seed: u64, kills: usize) {
    use rand::seq::index::sample;
    use rand::{Rng, SeedableRng};
    let dir = run_dir(&format!("e2e-chaos-{seed}-"));
    let run = dir.path().join("run");
    let run_arg = run.display().to_string();
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    // LONG_META_TRAINING's meta-epochs and checkpoint interval.
    let (meta_epochs, every) = (3000, 100);
    let launcher = launch(
        dir.path(),
        &run,
        &[
            // Only the kills may restart a child here: on a starved machine a child can be silent
            // past the hang timeout and be restarted for it too (seen with `make run` beside the
            // suite: 14 restarts for 12 kills). Hang detection has its own test.
            &[
                "run.max_restarts=100",
                "collect.transitions=400000",
                "run.hang_timeout_seconds=0",
            ][..],
            &LONG_META_TRAINING,
        ]
        .concat(),
    );
    let mut killed = Vec::new();
    let mut kill = |role: &'static str, pid: i32| {
        kill9(pid);
        killed.push(role);
    };
    wait_until("collection under way", within(60), || {
        run.join("ports/store.port").exists()
            && sum(
                &scrape(&run, "store"),
                metrics::store::DATASET_TRANSITIONS,
                &[],
            ) > 10_000.0
    });
    let mut actors = Vec::new();
    wait_until("a live actor", within(60), || {
        actors = child_pids(&[" actor ", &run_arg]);
        !actors.is_empty()
    });
    kill("actor", actors[rng.random_range(0..actors.len())]);

    // The w0 checkpoints after which the other kills land, in order; and which of them must hit
    // the store and the meta-learner.
    let mut at: Vec<usize> = sample(&mut rng, meta_epochs / every - 1, kills - 1)
        .into_iter()
        .map(|i| (i + 1) * every)
        .collect();
    at.sort_unstable();
    let must = sample(&mut rng, kills - 1, 2).into_vec();
    for (i, epoch) in at.into_iter().enumerate() {
        let checkpoint = run.join(format!("checkpoints/maml-init/epoch-{epoch:05}.json"));
        wait_until(&format!("w0 checkpoint {epoch}"), within(300), || {
            checkpoint.exists()
        });
        let want = [must[0], must[1]]
            .iter()
            .position(|&m| m == i)
            .map(|k| ["store", "meta-learner"][k]);
        let mut live = Vec::new();
        wait_until(&format!("a live {want:?}"), within(120), || {
            live = live_children(&run_arg);
            live.retain(|(role, _)| want.is_none_or(|w| w == *role));
            !live.is_empty()
        });
        let (role, pid) = live[rng.random_range(0..live.len())];
        kill(role, pid);
    }
    let out = launcher.wait(within(600));
    eprintln!("seed {seed}: killed {killed:?}");
    assert!(
        out.status.success(),
        "launch failed after killing {killed:?}:\n{}",
        stderr(&out)
    );
    assert_eq!(killed.len(), kills);
    let restarts = sum(
        &snapshot(&run, "launcher"),
        metrics::launcher::CHILD_RESTARTS,
        &[],
    );
    assert_eq!(
        restarts,
        kills as f64,
        "every kill restarted, and nothing else: {killed:?}\n{}",
        stderr(&out)
    );
    assert_every_transition_accounted(&run, 400_000);
    assert!(out.stdout.contains("cql-maml"), "{}", out.stdout);
}

#[test]
fn a_launch_survives_twelve_random_kills_on_three_seeds() {
    for seed in 0..3 {
        chaos(seed, 12);
    }
}

#[test]
fn an_evaluator_restarted_after_the_meta_learner_exited_catches_up_from_the_run_directory() {
    let dir = run_dir("e2e-evaluator-");
    let run = dir.path().join("run");
    let out = launch(dir.path(), &run, &[]).wait(within(240));
    assert!(out.status.success(), "launch failed:\n{}", stderr(&out));
    // The table's model-based section, under the line saying what it is told: Dyna-CQL's rows
    // and the planner in the world the shots identify, the last rows of the task.
    let table = &out.stdout;
    let rows: Vec<&str> = table.lines().collect();
    let section = rows
        .iter()
        .position(|l| l.starts_with(&format!("-- {}", uavmeta_proto::method::MODEL_BASED)))
        .unwrap_or_else(|| panic!("no model-based section:\n{table}"));
    let methods: Vec<&str> = rows[section + 1..]
        .iter()
        .filter_map(|l| l.split_whitespace().nth(1))
        .take(3)
        .collect();
    assert_eq!(
        methods,
        ["dyna-cql", "dyna-cql-w0", "model-planner"],
        "{table}"
    );
    let csv = run.join("evaluations.csv");
    let complete = std::fs::read_to_string(&csv).expect("evaluations.csv");
    let lines: Vec<&str> = complete.lines().collect();
    // Two w0 checkpoints, the context learner's zero-shot policy, and two epochs of each
    // fine-tuned method.
    assert_eq!(
        lines.len(),
        1 + 2 + 1 + Method::fine_tuned(Algo::CQL, &Algo::baselines()).len() * 2,
        "{complete}"
    );

    // As if the evaluator had been killed after its first row and restarted once the whole run,
    // meta-learner included, had exited: nobody announces anything any more.
    std::fs::write(&csv, format!("{}\n{}\n", lines[0], lines[1])).expect("cut the CSV");
    let run_arg = run.display().to_string();
    let evaluator = Proc::spawn(
        "evaluator",
        &["evaluator".to_string(), "--run".into(), run_arg],
    );
    let rows = || {
        std::fs::read_to_string(&csv)
            .map(|t| t.lines().count())
            .unwrap_or(0)
    };
    wait_until("the evaluator to catch up", within(120), || {
        rows() >= lines.len()
    });
    evaluator.signal(libc::SIGTERM);
    let finished = evaluator.wait(within(30));
    assert!(finished.status.success(), "{}", stderr(&finished));

    // Every checkpoint exactly once, with the figures the first evaluator found (the episodes are
    // seeded), the kept row first.
    let after = std::fs::read_to_string(&csv).expect("evaluations.csv");
    let after: Vec<&str> = after.lines().collect();
    assert_eq!(after[..2], lines[..2]);
    assert_eq!(
        after.len(),
        lines.len(),
        "a checkpoint evaluated twice:\n{}",
        after.join("\n")
    );
    assert_eq!(
        after.iter().collect::<BTreeSet<_>>(),
        lines.iter().collect::<BTreeSet<_>>()
    );
}

#[test]
fn a_launch_with_the_dqn_inner_loss_fine_tunes_and_reports_dqn_maml() {
    let dir = run_dir("e2e-dqn-maml-");
    let run = dir.path().join("run");
    let out = launch(dir.path(), &run, &["meta.inner_loss=\"dqn\""]).wait(within(240));
    assert!(out.status.success(), "launch failed:\n{}", stderr(&out));
    let csv = std::fs::read_to_string(run.join("evaluations.csv")).expect("evaluations.csv");
    let methods: BTreeMap<&str, usize> =
        csv.lines().skip(1).fold(BTreeMap::new(), |mut n, line| {
            *n.entry(line.split(',').nth(1).expect("a method column"))
                .or_default() += 1;
            n
        });
    // Two w0 checkpoints, the context learner's zero-shot policy, then two epochs each of
    // DQN-MAML, its random-init, pretrained and context baselines, and each of
    // `learner.baselines` from w0 and from a random init.
    let mut expected = BTreeMap::from([
        ("maml-init".to_string(), 2),
        ("context-init".to_string(), 1),
        ("dqn-maml".to_string(), 2),
        ("dqn".to_string(), 2),
        ("dqn-pretrain".to_string(), 2),
        ("dqn-context".to_string(), 2),
    ]);
    for algo in Algo::baselines() {
        expected.insert(format!("{algo}-w0"), 2);
        expected.insert(algo.to_string(), 2);
    }
    let methods: BTreeMap<String, usize> = methods
        .into_iter()
        .map(|(m, n)| (m.to_string(), n))
        .collect();
    assert_eq!(methods, expected, "{csv}");
    let w0 = run.join("checkpoints/maml-init/epoch-00004");
    let meta = uavmeta_learner::checkpoint::read_meta(&w0).expect("the final w0 checkpoint");
    assert_eq!(meta.algorithm, "dqn-maml", "{}", w0.display());
    let table = out.stdout;
    let methods: Vec<&str> = table
        .lines()
        .filter_map(|l| l.split_whitespace().nth(1))
        .collect();
    assert!(
        methods.contains(&"dqn-maml") && !methods.iter().any(|m| m.starts_with("cql")),
        "{table}"
    );
    let log =
        std::fs::read_to_string(run.join("meta-train/meta_train.csv")).expect("meta_train.csv");
    assert_eq!(log.lines().count(), 1 + 4, "{log}");
}

#[test]
fn two_runs_side_by_side_keep_their_data_apart() {
    let dirs = [run_dir("e2e-side-a-"), run_dir("e2e-side-b-")];
    let runs: Vec<PathBuf> = dirs.iter().map(|d| d.path().join("run")).collect();
    let policies = ["random", "stalest"];
    let launchers: Vec<Proc> = runs
        .iter()
        .zip(policies)
        .zip(&dirs)
        .map(|((run, policy), dir)| launch(dir.path(), run, &[&format!("collect.policy={policy}")]))
        .collect();
    for l in launchers {
        let out = l.wait(within(300));
        assert!(out.status.success(), "{}", stderr(&out));
    }
    let actors: Vec<BTreeSet<u32>> = runs
        .iter()
        .map(|run| {
            dataset_seqs(run)
                .values()
                .flat_map(|per_actor| per_actor.keys().copied())
                .collect()
        })
        .collect();
    assert!(
        actors[0].is_disjoint(&actors[1]),
        "a run stored another run's transitions"
    );
    for run in &runs {
        let store = snapshot(run, "store");
        assert_eq!(
            sum(
                &store,
                metrics::store::TRANSITIONS_DROPPED,
                &[("reason", metrics::store::FOREIGN)]
            ),
            0.0
        );
        assert_eq!(
            dataset_seqs(run).values().map(|a| a.len()).sum::<usize>(),
            3,
            "one actor per task"
        );
    }
}

/// Processes whose command line names `run`, other than `except`.
fn run_processes(run: &str, except: i32) -> Vec<i32> {
    child_pids(&[BIN, run])
        .into_iter()
        .filter(|&pid| pid != except)
        .collect()
}

#[test]
fn children_stop_when_the_launcher_is_killed_or_stopped() {
    for (signal, graceful) in [(libc::SIGKILL, false), (libc::SIGTERM, true)] {
        let dir = run_dir("e2e-orphans-");
        let run = dir.path().join("run");
        let run_arg = run.display().to_string();
        let launcher = launch(dir.path(), &run, &["meta.meta_epochs=100000"]);
        // Every child serving its metrics, so that each has final metrics to write: a child
        // stopped while it starts has none (this once failed on a busy machine).
        wait_until("the store, meta-learner and evaluator", within(60), || {
            ["store", "meta-learner", "evaluator"]
                .iter()
                .all(|p| run.join(format!("ports/{p}.port")).exists())
        });
        assert!(
            run_processes(&run_arg, launcher.pid()).len() >= 3,
            "the children run"
        );
        // SAFETY: a signal to the launcher this test started.
        unsafe { libc::kill(launcher.pid(), signal) };
        let out = launcher.wait(within(60));
        if graceful {
            assert!(
                out.stderr.contains("stopped by a termination request"),
                "{}",
                out.stderr
            );
        }
        wait_until("every child to exit", within(30), || {
            run_processes(&run_arg, -1).is_empty()
        });
        // Stopped in order, every child wrote its final metrics.
        if graceful {
            for process in ["store", "meta-learner", "evaluator"] {
                snapshot(&run, process);
            }
        }
    }
}

#[test]
fn the_same_config_and_seed_give_byte_identical_datasets() {
    let dirs = [run_dir("e2e-same-a-"), run_dir("e2e-same-b-")];
    let runs: Vec<PathBuf> = dirs.iter().map(|d| d.path().join("run")).collect();
    for (dir, run) in dirs.iter().zip(&runs) {
        let out = launch(dir.path(), run, &["collect.policy=eps:0.3"]).wait(within(240));
        assert!(out.status.success(), "{}", out.stderr);
    }
    for task in ["lambda-0", "lambda-100", "lambda-300"] {
        let file = format!("datasets/{task}.uavds");
        let bytes: Vec<Vec<u8>> = runs
            .iter()
            .map(|r| std::fs::read(r.join(&file)).expect("dataset"))
            .collect();
        assert!(!bytes[0].is_empty());
        assert!(
            bytes[0] == bytes[1],
            "{file} differs between two runs of one config"
        );
    }
}
