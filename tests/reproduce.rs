//! `uavmeta reproduce --quick` end to end, as CI runs it: every CSV, PNG and summary exists and is
//! well-formed (not the numbers: `--quick` checks plumbing), a rerun reuses the cache, and bad
//! input is refused with a message rather than a panic.

use std::path::Path;
use std::process::{Command, Output};

use uavmeta_proto::config::{Config, TaskRole};
use uavmeta_proto::method::{MODEL_BASED, MODEL_PLANNER, NO_FITTED_WORLD};
use uavmeta_reproduce::{quick_config, ReproduceConfig};

const CONFIG: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/configs/reproduce.toml");

fn uavmeta(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_uavmeta"))
        .arg("reproduce")
        .args(["--config", CONFIG])
        .args(args)
        .output()
        .expect("run uavmeta")
}

fn succeed(output: &Output) {
    assert!(
        output.status.success(),
        "uavmeta failed: {}",
        String::from_utf8_lossy(&output.stderr)
    );
}

fn read(path: &Path) -> String {
    std::fs::read_to_string(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

/// Checks `path` has exactly `header` and `rows` data rows, each with the header's column count.
fn check_csv(path: &Path, header: &str, rows: usize) {
    let text = read(path);
    let mut lines = text.lines();
    assert_eq!(lines.next(), Some(header), "{}", path.display());
    let columns = header.split(',').count();
    let data: Vec<&str> = lines.collect();
    assert_eq!(data.len(), rows, "{}", path.display());
    for line in data {
        assert_eq!(
            line.split(',').count(),
            columns,
            "{}: {line}",
            path.display()
        );
    }
}

/// An experiment's summary names its command, commit, seeds and wall time.
fn check_header(experiment: &str, summary: &str) {
    for part in [
        "- command: `",
        "--quick",
        "- commit: ",
        "- seeds: 0..1",
        "- wall time: ",
    ] {
        assert!(
            summary.contains(part),
            "{experiment}: no `{part}` in {summary}"
        );
    }
}

fn check_png(path: &Path) {
    let bytes = std::fs::read(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    assert!(
        bytes.starts_with(b"\x89PNG\r\n\x1a\n"),
        "{}: not a PNG",
        path.display()
    );
    assert!(
        bytes.len() > 1000,
        "{}: {} bytes",
        path.display(),
        bytes.len()
    );
}

/// The claims of docs/MODEL.md section 6, one table row each, and the behaviour agents' bar.
const CLAIMS: [&str; 18] = [
    "the behaviour agent is trained",
    "every seed within 2% of the planner reference",
    "DQN and DQN-MAML trained offline fail to converge",
    "CQL from a random init needs more than 100 epochs",
    "CQL-MAML converges in fewer than 40 epochs",
    "both end above the online DQN agent",
    "At epoch 40 CQL-MAML is at or above the online DQN agent",
    "in at most half the epochs CQL needs",
    "CQL-MAML beats CQL at every number of shots",
    "CQL depends on the number of shots far more",
    "More meta-training tasks, better",
    "At least 8 tasks are needed to beat online DQN",
    "Even 2 meta-training tasks beat plain CQL",
    "lambda = 300 after 50 epochs",
    "CQL-MAML converges within 100 epochs and reaches about zero outages",
    "CQL does not converge in 200 epochs",
    "CQL-MAML flying around the rain zone",
    "CQL-MAML adapts to rain better than CQL",
];

#[test]
fn quick_reproduction_writes_every_figure_table_and_claim() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path();
    let out_arg = out.to_str().unwrap();
    succeed(&uavmeta(&[
        "--experiment",
        "all",
        "--quick",
        "--out",
        out_arg,
    ]));

    // The sizes the files must have, from the same config and quick reduction the binary used.
    let config = quick_config(&Config::load(Path::new(CONFIG), &[]).unwrap()).unwrap();
    let r = ReproduceConfig::of(&config).unwrap();
    let seeds = r.seeds;
    let rain = config.tasks.iter().filter(|t| t.rain.is_some()).count();
    let meta_tasks = r.meta_tasks;
    let curve = "seed,epoch,return,return_ci95,aoi,power_mw,outages";
    // Each of `learner.baselines` adds two methods (from w0 and from a random init) to figures 5
    // to 9.
    let baselines = config.learner.baselines.len();

    let meta = out.join("meta-training");
    check_csv(
        &meta.join("fig4a_meta_loss.csv"),
        "seed,meta_epoch,meta_loss",
        seeds * config.meta.meta_epochs,
    );
    check_csv(
        &meta.join("fig4b_returns.csv"),
        "seed,meta_epoch,task,return,zero_shot",
        seeds * config.meta.meta_epochs * meta_tasks,
    );
    check_csv(
        &out.join("convergence/curves.csv"),
        &format!("method,{curve}"),
        // CQL-MAML, CQL-pretrain, CQL-context, CQL, DQN, DQN-MAML, then the baselines.
        (6 + 2 * baselines) * seeds * r.convergence_epochs,
    );
    check_csv(
        &out.join("convergence/references.csv"),
        "reference,task,seed,return,aoi,power_mw,outages",
        // The online agent per seed; random, stalest, greedy and the planner once.
        seeds + 4,
    );
    check_csv(
        &out.join("shots/curves.csv"),
        &format!("method,shots,{curve}"),
        r.shots.len() * (4 + 2 * baselines) * seeds * r.convergence_epochs,
    );
    check_csv(
        &out.join("tasks/curves.csv"),
        &format!("method,tasks,{curve}"),
        // The 3 CQL inits and the baselines from w0 per task count, then CQL and the baselines
        // from a random init once.
        ((3 + baselines) * r.task_counts.len() + 1 + baselines) * seeds * r.tasks_epochs,
    );
    check_csv(
        &out.join("aoi-power/bars.csv"),
        "method,seed,aoi,power_mw",
        // The online agent and the 4 CQL inits, the baselines from w0 and from a random init,
        // the planner in the world the shots fit; the 4 heuristics once.
        (6 + 2 * baselines) * seeds + 4,
    );
    check_csv(
        &out.join("resilience/curves.csv"),
        &format!("method,task,{curve}"),
        (4 + 2 * baselines) * rain * seeds * r.resilience_epochs,
    );
    // The planner in the world each seed's shots fit: once per task and shot count a figure reads.
    let planner = "task,shots,seed,return,aoi,power_mw,outages,fitted_world";
    for (figure, rows) in [
        ("convergence", seeds),
        ("shots", r.shots.len() * seeds),
        ("tasks", seeds),
        ("resilience", rain * seeds),
    ] {
        check_csv(&out.join(figure).join("model_planner.csv"), planner, rows);
    }
    let meta_train = config
        .tasks
        .iter()
        .filter(|t| t.role == TaskRole::MetaTrain);
    check_csv(
        &out.join("online-dqn/online_dqn.csv"),
        "task,seed,return,aoi,power_mw",
        (meta_train.count() + 1 + rain) * seeds,
    );
    check_csv(
        &out.join("resilience/fig9c_trajectories.csv"),
        "method,t,x,y",
        2 * (config.world.horizon as usize + 1),
    );
    for png in [
        "meta-training/fig4a_meta_loss.png",
        "meta-training/fig4b_returns.png",
        "meta-training/fig4c_zero_shot.png",
        "convergence/fig5.png",
        "shots/fig6.png",
        "tasks/fig7.png",
        "tasks/fig7b_by_tasks.png",
        "aoi-power/fig8a_aoi.png",
        "aoi-power/fig8b_power.png",
        "resilience/fig9a_return.png",
        "resilience/fig9b_outages.png",
        "resilience/fig9c_trajectories.png",
    ] {
        check_png(&out.join(png));
    }

    for experiment in [
        "meta-training",
        "convergence",
        "shots",
        "tasks",
        "aoi-power",
        "resilience",
    ] {
        let summary = read(&out.join(experiment).join("summary.md"));
        assert!(summary.starts_with("# Figure"), "{experiment}: {summary}");
        check_header(experiment, &summary);
        // Every figure that compares methods sets the model-based ones apart, under what they
        // are told, with the planner in the fitted world where the shots fit one (the lambda
        // task's do, the rain tasks' do not, and the summary says so).
        if experiment != "meta-training" {
            let section = format!("| *{MODEL_BASED}* |");
            assert_eq!(
                summary.matches(&section).count(),
                1,
                "{experiment}: {summary}"
            );
            let (before, after) = summary.split_once(&section).unwrap();
            assert!(!before.contains("| Dyna-CQL"), "{experiment}: {summary}");
            assert!(after.contains("| Dyna-CQL"), "{experiment}: {summary}");
            let planner_row = after.contains(&format!("| {MODEL_PLANNER} |"));
            assert_eq!(
                planner_row,
                experiment != "resilience",
                "{experiment}: {summary}"
            );
            let no_world = summary.contains(NO_FITTED_WORLD);
            assert_eq!(
                no_world,
                experiment == "resilience",
                "{experiment}: {summary}"
            );
        }
    }
    // Figure 9 judges CQL-MAML against CQL on return and on outages, each with the seeds'
    // interval, beside the planner and the strongest other method.
    let rain = read(&out.join("resilience/summary.md"));
    let contrast = rain
        .lines()
        .find(|l| l.contains("CQL-MAML adapts to rain better than CQL"))
        .unwrap_or_else(|| panic!("no return-and-outages claim in {rain}"));
    assert_eq!(contrast.matches(" ± ").count(), 6, "{contrast}");
    assert!(contrast.contains("; planner -"), "{contrast}");
    assert!(
        contrast.contains("the strongest other method"),
        "{contrast}"
    );
    let behaviour = read(&out.join("online-dqn/summary.md"));
    assert!(
        behaviour.starts_with("# The behaviour agents"),
        "{behaviour}"
    );
    check_header("online-dqn", &behaviour);
    // Every agent's task, the rain tasks included, has a row with the planner and the gap to it.
    assert!(
        behaviour.contains("| planner | gap (mean, worst) |"),
        "{behaviour}"
    );
    for task in config.tasks.iter() {
        let row = behaviour
            .lines()
            .find(|l| l.starts_with(&format!("| {} |", task.name)))
            .unwrap_or_else(|| panic!("no row for {} in {behaviour}", task.name));
        assert!(row.matches('%').count() == 2, "{row}");
    }
    let summary = read(&out.join("summary.md"));
    for claim in CLAIMS {
        let rows: Vec<&str> = summary
            .lines()
            .filter(|l| l.starts_with('|') && l.contains(claim))
            .collect();
        assert_eq!(rows.len(), 1, "claim `{claim}` in {summary}");
        let cells: Vec<&str> = rows[0].split('|').map(str::trim).collect();
        // | fig. | paper | measured | holds? | why |
        assert_eq!(cells.len(), 7, "{}", rows[0]);
        assert!(!cells[3].is_empty(), "{}", rows[0]);
        assert!(
            ["yes", "partly", "no", "untested"].contains(&cells[4]),
            "{}",
            rows[0]
        );
        assert_eq!(cells[5].is_empty(), cells[4] == "yes", "{}", rows[0]);
    }

    // Figure 4's init is evaluated every `meta_eval_every` (1 in quick mode) meta-epochs; the
    // inits no figure draws a curve of only after their last.
    let evaluated = |init: &str| -> Vec<bool> {
        read(&out.join(format!("cache/seed-0/{init}/meta_train.csv")))
            .lines()
            .skip(1)
            .map(|line| !line.split(',').rev().nth(1).unwrap().is_empty())
            .collect()
    };
    assert_eq!(evaluated("cql-maml-tasks-8"), vec![true; 3]);
    for init in ["cql-maml-tasks-2", "dqn-maml-tasks-8"] {
        assert_eq!(evaluated(init), vec![false, false, true], "{init}");
    }

    // --status reads the finished plan: every kind's jobs done and timed, nothing running.
    let status = uavmeta(&["--status", "--out", out_arg]);
    succeed(&status);
    let status = String::from_utf8_lossy(&status.stdout).into_owned();
    let done = status
        .lines()
        .find(|l| l.starts_with("done "))
        .expect(&status);
    assert!(done.ends_with("running 0, left 0; finished"), "{status}");
    for row in status
        .lines()
        .skip(1)
        .take_while(|l| !l.starts_with("done "))
    {
        let cells: Vec<&str> = row.split_whitespace().collect();
        assert_eq!(cells[2..4], ["0", "0"], "{status}");
        let timed = cells[4].parse::<f64>().is_ok();
        assert_eq!(
            timed,
            cells[1] != "0",
            "a kind with jobs done untimed: {status}"
        );
    }

    // A second run reuses the seeds' datasets and w0s: same files, same figures.
    let dataset = out.join("cache/seed-0/datasets/lambda-0.uavds");
    let w0 = out.join("cache/seed-0/cql-maml-tasks-8/w0.safetensors");
    let stamps =
        |paths: [&Path; 2]| paths.map(|p| std::fs::metadata(p).unwrap().modified().unwrap());
    let before = stamps([&dataset, &w0]);
    let loss = read(&meta.join("fig4a_meta_loss.csv"));
    succeed(&uavmeta(&[
        "--experiment",
        "meta-training",
        "--quick",
        "--out",
        out_arg,
    ]));
    assert_eq!(stamps([&dataset, &w0]), before);
    assert_eq!(read(&meta.join("fig4a_meta_loss.csv")), loss);
}

/// The figures are drawn from the data the main job's agents make: the reproduction's behaviour
/// agents train as `make run`'s do.
#[test]
fn the_reproduction_trains_its_agents_as_the_main_job_does() {
    let load = |name: &str| {
        let path = Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("configs")
            .join(name);
        Config::load(&path, &[]).unwrap()
    };
    let (reproduce, main) = (load("reproduce.toml"), load("default.toml"));
    assert_eq!(reproduce.collect.dqn, main.collect.dqn);
    assert_eq!(reproduce.collect.policy, main.collect.policy);
}

#[test]
fn unknown_experiments_and_bad_sections_are_refused_by_name() {
    let output = uavmeta(&["--experiment", "bogus", "--quick"]);
    assert_eq!(output.status.code(), Some(2));
    let stderr = String::from_utf8_lossy(&output.stderr);
    for choice in ["bogus", "all", "meta-training", "aoi-power", "resilience"] {
        assert!(stderr.contains(choice), "`{choice}` missing from: {stderr}");
    }

    // A quick reproduction with one bad `--set` ends with status 1 and a message, not a panic.
    let dir = tempfile::tempdir().unwrap();
    let refused = |set: &str| -> String {
        let out_dir = dir.path().to_str().unwrap();
        let output = uavmeta(&["--quick", "--set", set, "--out", out_dir]);
        let stderr = String::from_utf8_lossy(&output.stderr).into_owned();
        assert_eq!(output.status.code(), Some(1), "{stderr}");
        assert!(!stderr.contains("panicked"), "{stderr}");
        stderr
    };
    let stderr = refused("reproduce.unseen_task=\"lambda-0\"");
    assert!(
        stderr.starts_with("uavmeta: ")
            && stderr.contains("reproduce.toml")
            && stderr.contains("reproduce.unseen_task")
            && stderr.contains("meta-test"),
        "{stderr}"
    );

    // A key that was removed says so.
    let stderr = refused("learner.population=4");
    assert!(
        stderr.contains("learner.population") && stderr.contains("was removed"),
        "{stderr}"
    );
}
