//! Config files as users write them: the defaults, `--set` overrides, and every validation error
//! naming the file, the key and the value.

use std::io::Write;
use std::path::PathBuf;

use uavmeta_proto::config::{Config, Fate, PowerTerm, TaskRole, MOVED};

/// Writes `text` to a temporary file and loads it with `overrides`; returns the file's path with
/// the result so errors can be checked for it.
fn load(text: &str, overrides: &[&str]) -> (PathBuf, Result<Config, String>) {
    let mut file = tempfile::Builder::new()
        .suffix(".toml")
        .tempfile()
        .expect("temp file");
    file.write_all(text.as_bytes()).expect("write temp config");
    let path = file.path().to_path_buf();
    let overrides: Vec<String> = overrides.iter().map(|s| s.to_string()).collect();
    let result = Config::load(&path, &overrides).map_err(|e| e.to_string());
    (path, result)
}

/// The error of `text`, which must name the file and every one of `parts`.
fn error_of(text: &str, overrides: &[&str], parts: &[&str]) -> String {
    let (path, result) = load(text, overrides);
    let message = result.expect_err("config should be rejected");
    assert!(
        message.contains(&path.display().to_string()),
        "no file name in: {message}"
    );
    for part in parts {
        assert!(message.contains(part), "`{part}` missing from: {message}");
    }
    message
}

#[test]
fn more_devices_than_cells() {
    error_of(
        "[world]\ngrid_cells = 2\ndevices = 5\n",
        &[],
        &["world.devices", "5", "4"],
    );
}

#[test]
fn two_devices_on_one_cell() {
    error_of(
        "[world]\ndevices = 3\ndevice_cells = [[0, 0], [4, 2], [4, 2]]\n",
        &[],
        &["world.device_cells[2]", "[4, 2]", "no other device"],
    );
}

#[test]
fn device_outside_the_grid() {
    error_of(
        "[world]\ndevices = 1\ndevice_cells = [[3, 10]]\n",
        &[],
        &["world.device_cells[0]", "[3, 10]"],
    );
}

#[test]
fn device_cells_length_must_match_devices() {
    error_of(
        "[world]\ndevices = 3\ndevice_cells = [[0, 0], [1, 1]]\n",
        &[],
        &["world.device_cells", "[[0, 0], [1, 1]]", "3"],
    );
}

/// A task's own layout (docs/MODEL.md section 11) keeps the world's rules under its own key, is
/// one of cells and a seed, and moves the world's hash; a config without one hashes as before.
#[test]
fn a_task_layout_is_checked_as_the_worlds_and_counts_in_the_world_hash() {
    let task = "[[tasks]]\nname = \"moved\"\nlambda = 300.0\nrole = \"meta-test\"\n";
    let world = "[world]\ndevices = 3\n";
    error_of(
        &format!("{world}{task}device_cells = [[0, 0], [4, 2], [4, 2]]\n"),
        &[],
        &["tasks[0].device_cells[2]", "[4, 2]", "no other device"],
    );
    error_of(
        &format!("{world}{task}device_cells = [[0, 0], [4, 2]]\n"),
        &[],
        &["tasks[0].device_cells", "[[0, 0], [4, 2]]", "3 cells"],
    );
    error_of(
        &format!("{world}{task}device_cells = [[0, 0], [4, 2], [1, 1]]\nlayout_seed = 4\n"),
        &[],
        &["tasks[0].layout_seed", "4", "device_cells"],
    );
    error_of(
        &format!("{world}{task}layout_seed = -1\n"),
        &[],
        &["tasks[0].layout_seed", "-1"],
    );

    let hash = |text: &str| load(text, &[]).1.expect("a valid config").world_hash();
    let plain = hash(&format!("{world}{task}"));
    let world_only = Config::from_toml_str(world, "world.toml", &[]).expect("world");
    assert_eq!(
        plain,
        world_only.world_hash(),
        "tasks without layouts leave the hash"
    );
    let seeded = hash(&format!("{world}{task}layout_seed = 4\n"));
    let placed = hash(&format!(
        "{world}{task}device_cells = [[0, 0], [4, 2], [1, 1]]\n"
    ));
    assert!(plain != seeded && plain != placed && seeded != placed);
}

#[test]
fn rain_zone_outside_the_grid() {
    let text = "[[tasks]]\nname = \"wet\"\nlambda = 300.0\nrole = \"meta-test\"\nrain = { x0 = 8, y0 = 2, x1 = 10, y1 = 3 }\n";
    error_of(text, &[], &["tasks[0].rain", "x1: 10", "inside the grid"]);
}

#[test]
fn negative_lambda() {
    let text = "[[tasks]]\nname = \"a\"\nlambda = 1.0\nrole = \"meta-train\"\n\n[[tasks]]\nname = \"b\"\nlambda = -5.0\nrole = \"meta-test\"\n";
    error_of(text, &[], &["tasks[1].lambda", "-5", ">= 0"]);
}

#[test]
fn no_adaptation_to_evaluate() {
    error_of(
        "[meta]\neval_adaptations = 0\n",
        &[],
        &["meta.eval_adaptations", "0", "at least 1"],
    );
}

#[test]
fn negative_meta_alpha() {
    error_of(
        "[meta]\nalpha = -1.0\n",
        &[],
        &["meta.alpha", "-1", "a finite number >= 0"],
    );
}

#[test]
fn unknown_key() {
    error_of(
        "[world]\ndevices = 10\nheight = 120.0\n",
        &[],
        &["height", "120.0", "unknown field"],
    );
}

#[test]
fn wrong_type() {
    error_of(
        "[world]\ndevices = \"ten\"\n",
        &[],
        &["devices", "\"ten\"", "invalid type"],
    );
}

#[test]
fn bad_set_overrides() {
    error_of(
        "",
        &["learner.average_decay=1"],
        &["learner.average_decay", "1", "a decay in [0, 1)"],
    );
    error_of(
        "",
        &["world.devices"],
        &["--set world.devices", "KEY=VALUE"],
    );
    error_of(
        "",
        &["world.devices=many"],
        &["--set world.devices=many", "devices", "many"],
    );
    error_of(
        "",
        &["world..devices=3"],
        &["--set world..devices=3", "dotted"],
    );
    error_of(
        "",
        &["tasks.99.lambda=1"],
        &["--set tasks.99.lambda=1", "99", "out of range"],
    );
    error_of(
        "",
        &["world.nonsense=1"],
        &["--set world.nonsense=1", "nonsense", "unknown field"],
    );
    error_of(
        "",
        &["tasks.0.lambda=-2"],
        &["--set tasks.0.lambda=-2", "tasks[0].lambda", "-2"],
    );
}

#[test]
fn an_empty_file_has_the_spec_defaults() {
    let (path, result) = load("", &[]);
    let c = result.expect("an empty file is a valid config");
    assert_eq!(c.origin, path.display().to_string());
    let w = &c.world;
    assert_eq!(
        (w.grid_cells, w.cell_m, w.devices, w.height_m),
        (10, 100.0, 10, 100.0)
    );
    assert_eq!(
        (w.horizon, w.aoi_max, w.start_cell, w.device_cells.clone()),
        (100, 100, None, None)
    );
    assert_eq!(
        (w.g0_db, w.bandwidth_hz, w.bits, w.noise_dbm),
        (-30.0, 1e6, 5e6, -100.0)
    );
    assert_eq!(w.power_term, PowerTerm::Scheduled);
    assert_eq!(w.delta_per_device(), vec![1.0; 10]);
    assert!((w.rain_attenuation_db_per_km() - 2.36).abs() < 0.01);
    let train: Vec<f64> = c
        .tasks_with_role(TaskRole::MetaTrain)
        .map(|t| t.lambda)
        .collect();
    assert_eq!(
        train,
        [0.0, 100.0, 200.0, 400.0, 500.0, 600.0, 800.0, 1000.0]
    );
    let test: Vec<f64> = c
        .tasks_with_role(TaskRole::MetaTest)
        .map(|t| t.lambda)
        .collect();
    assert_eq!(test, [300.0]);
    assert_eq!(
        (c.learner.hidden.clone(), c.learner.gamma, c.learner.alpha),
        (vec![256, 256], 0.99, 1.0)
    );
    assert_eq!(
        (c.meta.meta_epochs, c.meta.eta_inner, c.meta.eta_outer),
        (150, 1e-2, 1e-3)
    );
}

#[test]
fn a_file_names_only_what_it_changes() {
    let text = "[world]\ndevices = 4\ndevice_cells = [[0, 0], [1, 0], [2, 0], [3, 3]]\n\n\
                [[tasks]]\nname = \"wet\"\nlambda = 250.0\nrole = \"meta-test\"\n\
                rain = { x0 = 1, y0 = 1, x1 = 2, y1 = 2 }\nrain_moves_every = 5\n";
    let c = load(text, &[]).1.expect("valid config");
    assert_eq!(
        c.world.device_cells.as_deref(),
        Some(&[[0, 0], [1, 0], [2, 0], [3, 3]][..])
    );
    assert_eq!(c.world.horizon, 100);
    let wet = c.task("wet").expect("task defined");
    assert_eq!((wet.lambda, wet.rain_moves_every), (250.0, Some(5)));
    assert!(wet.rain.expect("rain zone").contains(2, 1));
    assert_eq!(c.tasks.len(), 1);
}

#[test]
fn set_overrides_dotted_keys_and_task_entries() {
    let c = load(
        "[world]\ndevices = 4\n",
        &[
            "world.devices=20",
            "tasks.0.lambda=7.5",
            "world.power_term=all_devices",
            "meta.first_order=true",
        ],
    )
    .1
    .expect("overrides are valid");
    assert_eq!(c.world.devices, 20);
    assert_eq!(c.tasks[0].lambda, 7.5);
    assert_eq!(
        c.tasks.len(),
        9,
        "the default tasks stay when one of them is overridden"
    );
    assert_eq!(c.tasks[8].lambda, 300.0);
    assert_eq!(c.world.power_term, PowerTerm::AllDevices);
    assert!(c.meta.first_order);
    assert!(c.origin.contains("--set world.devices=20"));
}

#[test]
fn set_indexes_the_tasks_of_the_file() {
    let text = "[[tasks]]\nname = \"a\"\nlambda = 1.0\nrole = \"meta-train\"\n\n\
                [[tasks]]\nname = \"b\"\nlambda = 2.0\nrole = \"meta-test\"\n";
    let c = load(
        text,
        &[
            "tasks.1.lambda=20",
            "tasks.1.rain={ x0 = 1, y0 = 1, x1 = 2, y1 = 3 }",
        ],
    )
    .1
    .expect("valid");
    assert_eq!((c.tasks[0].lambda, c.tasks[1].lambda), (1.0, 20.0));
    assert!(c.tasks[1].rain.expect("rain set").contains(2, 3));
    error_of(
        text,
        &["tasks.2.lambda=1"],
        &["--set tasks.2.lambda=1", "out of range", "2 entries"],
    );
}

#[test]
fn config_round_trips_through_its_toml() {
    let c = load(
        "[world]\ndevices = 3\nstart_cell = [1, 2]\n",
        &["tasks.2.lambda=42"],
    )
    .1
    .expect("valid");
    let again = Config::from_toml_str(&c.to_toml_string(), "saved.toml", &[])
        .expect("saved config reloads");
    assert_eq!(
        Config {
            origin: String::new(),
            ..again
        },
        Config {
            origin: String::new(),
            ..c
        }
    );
}

#[test]
fn grid_too_large_for_the_power_tables() {
    error_of(
        "[world]\ngrid_cells = 5000\n",
        &[],
        &["world.grid_cells", "5000", "1024"],
    );
}

#[test]
fn seed_that_toml_cannot_hold() {
    let (_, result) = load("", &[]);
    let mut config = result.expect("empty file is all defaults");
    config.collect.seed = u64::MAX;
    let message = config
        .validate()
        .expect_err("seed above i64::MAX")
        .to_string();
    assert!(
        message.contains("collect.seed") && message.contains(&u64::MAX.to_string()),
        "{message}"
    );
}

#[test]
fn a_section_another_crate_owns_is_kept_as_written() {
    // `[reproduce]` is uavmeta_reproduce's (its tests check the keys): the contract keeps the
    // table, unread, through `--set` and a save, and leaves it out when the file has none.
    let (_, result) = load("[reproduce]\nseeds = 3\n", &["reproduce.bogus=1"]);
    let c = result.expect("the owner checks its keys");
    let saved = c.to_toml_string();
    assert!(
        saved.contains("[reproduce]") && saved.contains("bogus = 1"),
        "{saved}"
    );
    let again = Config::from_toml_str(&saved, "saved.toml", &[]).unwrap();
    assert_eq!(again.reproduce, c.reproduce);
    let (_, result) = load("", &[]);
    let saved = result.unwrap().to_toml_string();
    assert!(!saved.contains("[reproduce]"), "{saved}");
}

#[test]
fn learning_rate_schedules_are_checked() {
    error_of(
        "[collect.dqn]\nlr_final_fraction = 1.5\n",
        &[],
        &[
            "collect.dqn.lr_final_fraction",
            "1.5",
            "a fraction in [0, 1]",
        ],
    );
}

#[test]
fn the_bcq_threshold_is_a_share() {
    for bad in ["1.5", "-0.1", "nan"] {
        error_of(
            &format!("[learner]\nbcq_threshold = {bad}\n"),
            &[],
            &["learner.bcq_threshold", "a share in [0, 1]"],
        );
    }
    for good in ["0.0", "0.3", "1.0"] {
        let (_, result) = load(&format!("[learner]\nbcq_threshold = {good}\n"), &[]);
        result.expect("a share in [0, 1]");
    }
}

#[test]
fn not_a_number_and_infinity_break_the_finite_rules() {
    error_of(
        "[learner]\nalpha = nan\n",
        &[],
        &["learner.alpha", "NaN", "a finite number >= 0"],
    );
    error_of(
        "[meta]\neta_outer = inf\n",
        &[],
        &["meta.eta_outer", "inf", "a learning rate > 0"],
    );
    error_of(
        "",
        &["world.noise_dbm=-inf"],
        &["world.noise_dbm", "-inf", "a finite number of dB"],
    );
    // Ranges without "finite" in their words still refuse NaN: it is inside no range.
    error_of(
        "[collect.dqn]\neps_end = nan\n",
        &[],
        &["collect.dqn.eps_end", "NaN", "a probability in [0, 1]"],
    );
    error_of(
        "[meta]\nsupport_fraction = nan\n",
        &[],
        &["meta.support_fraction", "NaN", "strictly between 0 and 1"],
    );
    error_of(
        "[planner]\nh_power_weights = [0.5, nan]\n",
        &[],
        &[
            "planner.h_power_weights",
            "[0.5, NaN]",
            "finite weights >= 0",
        ],
    );
}

#[test]
fn a_value_outside_its_set_is_refused() {
    error_of(
        "[run]\ndomain = \"a b\"\n",
        &[],
        &["run.domain", "\"a b\"", "letters, digits, '-' or '_'"],
    );
    let (_, result) = load("[run]\ndomain = \"run-1_a\"\n", &[]);
    result.expect("letters, digits, '-' and '_' are in the set");
}

#[test]
fn rules_on_entries_name_the_entry() {
    error_of(
        "[[tasks]]\nname = \"a\"\nlambda = 1.0\nrole = \"meta-test\"\n\
         rain = { x0 = 0, y0 = 0, x1 = 1, y1 = 1 }\nrain_moves_every = 0\n",
        &[],
        &["tasks[0].rain_moves_every", "= 0", "at least 1 step"],
    );
    let mut config = load("", &[]).1.expect("defaults");
    config.run.seeds = vec![3, u64::MAX];
    let message = config
        .validate()
        .expect_err("seed above i64::MAX")
        .to_string();
    assert!(
        message.contains("run.seeds[1]") && message.contains(&i64::MAX.to_string()),
        "{message}"
    );
}

#[test]
fn the_first_broken_rule_is_reported_in_section_order() {
    // [learner] comes before [meta] in a config, whatever the order of the file.
    let message = error_of(
        "[meta]\nalpha = -1.0\n\n[learner]\nalpha = -2.0\nbatch_size = 0\n",
        &[],
        &["learner.alpha", "-2"],
    );
    assert!(!message.contains("meta.alpha"), "{message}");
}

#[test]
fn a_launch_refuses_more_shots_than_the_dataset_and_other_commands_do_not_care() {
    let (path, config) = load(
        "[collect]\ntransitions = 500\n[learner]\nshots = 600\n",
        &[],
    );
    let config = config.expect("a collect or a train of 500 transitions has no use for the shots");
    let message = config
        .validate_launch()
        .expect_err("a launch cannot fine-tune on 600 of 500 transitions")
        .to_string();
    for part in [
        path.display().to_string().as_str(),
        "learner.shots",
        "600",
        "at most collect.transitions = 500",
    ] {
        assert!(message.contains(part), "`{part}` missing from: {message}");
    }
    let (_, fits) = load(
        "[collect]\ntransitions = 600\n[learner]\nshots = 600\n",
        &[],
    );
    fits.expect("loads")
        .validate_launch()
        .expect("600 shots of 600 transitions");
}

#[test]
fn a_launch_fine_tunes_on_learner_shots_or_the_whole_dataset() {
    let (_, all) = load("", &[]);
    let all = all.expect("the defaults load");
    assert_eq!(all.learner.shots, 0);
    assert_eq!(all.fine_tune_shots(), all.collect.transitions);
    let (_, few) = load("", &["collect.transitions=2000", "learner.shots=500"]);
    assert_eq!(
        few.expect("shots within the dataset load")
            .fine_tune_shots(),
        500
    );
}

/// Every removed or renamed key is refused, in a file, in an override and in a `[[tasks]]`
/// table, with what became of it; the error names the file and the key.
#[test]
fn a_removed_or_renamed_key_says_what_became_of_it() {
    for (key, fate) in MOVED {
        let (section, name) = key.split_once('.').unwrap();
        let said = match fate {
            Fate::Removed(_) => "was removed".to_string(),
            Fate::Renamed(new) => format!("write `{new}` instead"),
        };
        let in_file = match section {
            "tasks" => format!("[[tasks]]\nname = \"a\"\n{name} = 1\n"),
            _ => format!("[{section}]\n{name} = 1\n"),
        };
        error_of(&in_file, &[], &[key, &said]);
        if section != "tasks" {
            error_of("", &[&format!("{key}=1")], &[key, &said, "--set"]);
        }
    }
    // A key that never existed keeps serde's own error.
    let message = error_of("[learner]\nno_such_key = 1\n", &[], &["no_such_key"]);
    assert!(!message.contains("was removed"), "{message}");
}

/// Every file in configs/ loads, and configs/paper-90dbm.toml is configs/paper.toml but for the
/// noise floor (and its run directory), so the two cannot drift apart.
#[test]
fn every_shipped_config_loads_and_the_paper_floors_differ_only_in_the_noise() {
    let configs = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../configs");
    let mut loaded = 0;
    for entry in std::fs::read_dir(&configs).expect("configs/") {
        let path = entry.expect("entry").path();
        if path.extension().is_some_and(|e| e == "toml") {
            Config::load(&path, &[]).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
            loaded += 1;
        }
    }
    assert!(loaded >= 4, "{loaded} configs in {}", configs.display());
    let paper = Config::load(&configs.join("paper.toml"), &[]).expect("paper.toml");
    let at_90 = ["world.noise_dbm=-100.0", "run.dir=\"runs/paper\""].map(String::from);
    let louder = Config::load(&configs.join("paper-90dbm.toml"), &at_90).expect("paper-90dbm");
    assert_eq!(louder.to_toml_string(), paper.to_toml_string());
    let louder = Config::load(&configs.join("paper-90dbm.toml"), &[]).expect("paper-90dbm");
    assert_eq!(louder.world.noise_dbm, -90.0);
}

#[test]
fn a_tunnel_names_the_hosts_that_may_serve_and_each_hosts_tasks_exist() {
    let listen = "tunnel.listen=\"tcp/127.0.0.1:7447\"";
    error_of("", &[listen], &["tunnel.hosts", "at least one remote host"]);
    let unknown = "tunnel.hosts={b=[\"lambda-9\"]}";
    error_of(
        "",
        &[listen, unknown],
        &["tunnel.hosts.b", "lambda-9", "a task of [[tasks]]"],
    );
    let bad_name = "tunnel.hosts={\"a/b\"=[\"*\"]}";
    error_of(
        "",
        &[listen, bad_name],
        &["tunnel.hosts.a/b", "certificate"],
    );
    let waits = "tunnel.wait_for_hosts=[\"c\"]";
    let served = "tunnel.hosts={b=[\"*\"]}";
    error_of(
        "",
        &[listen, served, waits],
        &["tunnel.wait_for_hosts", "\"c\""],
    );
    error_of(
        "",
        &[listen, served, "tunnel.max_host_share=0.0"],
        &["tunnel.max_host_share"],
    );
    let (_, config) = load("", &[listen, served]);
    let config = config.expect("a valid tunnel");
    let all = config.tunnel.tasks_of("b", &config.tasks);
    assert_eq!(all.len(), config.tasks.len());
    assert!(config.tunnel.tasks_of("c", &config.tasks).is_empty());
}
