//! `[reproduce]` as users write it: the section this crate owns, read and checked alone and
//! against the experiment's tasks, every error naming the file, the key and the value.

use uavmeta_proto::config::Config;
use uavmeta_reproduce::ReproduceConfig;

const FILE: &str = "reproduce-test.toml";

/// `text` (with `overrides`) as a config: the contract accepts any `[reproduce]`.
fn config(text: &str, overrides: &[&str]) -> Config {
    let overrides: Vec<String> = overrides.iter().map(|s| s.to_string()).collect();
    Config::from_toml_str(text, FILE, &overrides).expect("the contract keeps [reproduce] unread")
}

/// The error `ReproduceConfig::of` gives for `text`: it must name the file and every one of
/// `parts`.
fn error_of(text: &str, overrides: &[&str], parts: &[&str]) -> String {
    let message = ReproduceConfig::of(&config(text, overrides))
        .expect_err("[reproduce] should be refused")
        .to_string();
    for part in [FILE].iter().chain(parts) {
        assert!(message.contains(part), "`{part}` missing from: {message}");
    }
    message
}

/// The default tasks have eight meta-train tasks; the default task counts go to ten.
const EIGHT: &str = "[reproduce]\ntask_counts = [2, 4, 8]\n";

#[test]
fn reproduce_section_is_checked_alone_and_against_the_tasks() {
    error_of(
        "[reproduce]\ntask_counts = [4, 2]\n",
        &[],
        &["reproduce.task_counts", "[4, 2]", "strictly increasing"],
    );
    error_of(
        "[reproduce]\nresilience_eval_episodes = 0\n",
        &[],
        &["reproduce.resilience_eval_episodes", "0", "at least 1"],
    );
    // The default tasks have eight meta-train tasks and no `lambda-700`: other commands accept
    // such a file; only a reproduction refuses it, naming the key.
    error_of(
        "[reproduce]\ntask_counts = [2, 10]\nunseen_task = \"lambda-700\"\n",
        &[],
        &["reproduce.task_counts", "8 tasks"],
    );
    error_of(
        "[reproduce]\ntask_counts = [2]\nunseen_task = \"lambda-0\"\n",
        &[],
        &["reproduce.unseen_task", "meta-test"],
    );
    error_of(
        "[reproduce]\ntask_counts = [2]\nmain_shots = 501\n",
        &[],
        &["collect.transitions = 500"],
    );
    let defaults = ReproduceConfig::default();
    assert_eq!((defaults.seeds, defaults.main_shots), (5, 500));
    assert_eq!(defaults.unseen_task, "lambda-300");
    // Ten task counts need ten meta-train tasks: the defaults' eight are refused.
    assert!(ReproduceConfig::of(&config("", &[])).is_err());
    let eight = ReproduceConfig::of(&config(EIGHT, &[])).expect("fits the default tasks");
    assert_eq!(
        eight,
        ReproduceConfig {
            task_counts: vec![2, 4, 8],
            ..defaults
        }
    );
}

#[test]
fn unknown_keys_wrong_types_and_seeds_are_refused_by_name() {
    error_of(EIGHT, &["reproduce.seedz=3"], &["[reproduce]", "seedz"]);
    error_of(
        EIGHT,
        &["reproduce.seeds=\"three\""],
        &["[reproduce]", "three"],
    );
    error_of(
        EIGHT,
        &["reproduce.seeds=0"],
        &["reproduce.seeds", "0", "at least 1"],
    );
    // Seed s collects with collect.seed + s, which a TOML file must hold.
    let top = i64::MAX.to_string();
    error_of(
        EIGHT,
        &[&format!("collect.seed={top}"), "reproduce.seeds=2"],
        &["reproduce.seeds", "2", &top],
    );
}

#[test]
fn settings_written_into_a_config_read_back() {
    let mut c = config(EIGHT, &["reproduce.seeds=2"]);
    let mut r = ReproduceConfig::of(&c).unwrap();
    assert_eq!(r.seeds, 2);
    r.meta_eval_every = 7;
    r.write_into(&mut c);
    let saved = Config::from_toml_str(&c.to_toml_string(), "saved.toml", &[]).unwrap();
    assert_eq!(ReproduceConfig::of(&saved).unwrap(), r);
}
