//! Whether a launch may use an existing run directory: a run's datasets and checkpoints belong
//! to the config it was made with (its `config.toml`), so a launch with a config whose
//! artefact-making keys differ is refused, naming them, unless told to move the old run aside.
//!
//! Every key counts except [`OPERATIONAL`] ones (where the run writes, its ports, its iceoryx2
//! capacities and supervision, the tunnel), which change how a run is carried out and never what
//! its datasets, checkpoints and results hold, and `[reproduce]`, which only `uavmeta reproduce`
//! reads.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use serde_json::Value;
use uavmeta_proto::config::Config;

use super::LaunchError;
use uavmeta_proto::fs::FileError;

/// What to do with a run directory that already holds a run.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Reuse {
    /// Continue it if its config is the same; refuse otherwise (and say how to choose).
    #[default]
    IfSame,
    /// Continue it (`--resume`): its config must be the same; a missing run is an error.
    Resume,
    /// Move it aside and start afresh (`--fresh`).
    Fresh,
}

/// Keys (and sections, ending in `.`) whose values do not reach a run's artefacts.
const OPERATIONAL: [&str; 11] = [
    "run.dir",
    "run.metrics_host",
    "run.metrics_port",
    "run.transitions_per_message",
    "run.subscriber_buffer",
    "run.max_publishers",
    "run.max_restarts",
    "run.hang_timeout_seconds",
    "run.domain",
    "tunnel.",
    // A launch never reads it; runs saved before it became the reproduce crate's section wrote
    // it out in full, and a config now saves it only when its file has it.
    "reproduce.",
];

/// The run directory's config file, whether `dir` holds a run.
fn config_file(dir: &Path) -> PathBuf {
    dir.join("config.toml")
}

/// Checks `config.run.dir` against `reuse` before anything is written there; with
/// [`Reuse::Fresh`], moves an existing run aside and returns where it went.
pub fn prepare(config: &Config, reuse: Reuse) -> Result<Option<PathBuf>, LaunchError> {
    let dir = &config.run.dir;
    let file = config_file(dir);
    if !file.exists() {
        if reuse == Reuse::Resume {
            return Err(LaunchError::Reuse {
                dir: dir.clone(),
                message: format!(
                    "--resume: {} does not exist; there is no run to resume",
                    file.display()
                ),
            });
        }
        return Ok(None);
    }
    if reuse == Reuse::Fresh {
        return move_aside(dir).map(Some);
    }
    let old = Config::load(&file, &[]).map_err(|e| LaunchError::Reuse {
        dir: dir.clone(),
        message: format!("its config cannot be read ({e}); launch with --fresh to move it aside"),
    })?;
    let differing = differing_keys(&old, config);
    if differing.is_empty() {
        return Ok(None);
    }
    Err(LaunchError::Reuse {
        dir: dir.clone(),
        message: format!(
            "it holds a run made with another config ({}), whose datasets and checkpoints would \
             be reused as this config's; launch with --fresh to move that run aside, or with \
             its own config ({}) to resume it",
            differing.join(", "),
            file.display()
        ),
    })
}

/// Renames `dir` to `<dir>.moved-<n>`, the first n free.
fn move_aside(dir: &Path) -> Result<PathBuf, LaunchError> {
    let name = dir
        .file_name()
        .map_or_else(|| "run".into(), |n| n.to_string_lossy().into_owned());
    let to = (1u32..)
        .map(|n| dir.with_file_name(format!("{name}.moved-{n}")))
        .find(|candidate| !candidate.exists())
        .expect("some suffix is free");
    std::fs::rename(dir, &to).map_err(FileError::at(dir, "move the old run aside (--fresh)"))?;
    tracing::warn!(from = %dir.display(), to = %to.display(), "--fresh: moved the old run aside");
    Ok(to)
}

/// `key: old -> new` for every artefact-making key whose value differs, in key order.
pub fn differing_keys(old: &Config, new: &Config) -> Vec<String> {
    let (old, new) = (flatten(old), flatten(new));
    let keys: std::collections::BTreeSet<&String> = old.keys().chain(new.keys()).collect();
    let missing = Value::String("(absent)".into());
    keys.into_iter()
        .filter(|key| !OPERATIONAL.iter().any(|op| is_under(key, op)))
        .filter_map(|key| {
            let (a, b) = (
                old.get(key).unwrap_or(&missing),
                new.get(key).unwrap_or(&missing),
            );
            (a != b).then(|| format!("{key}: {a} -> {b}"))
        })
        .collect()
}

fn is_under(key: &str, op: &str) -> bool {
    match op.strip_suffix('.') {
        Some(section) => key == section || key.starts_with(op),
        None => key == op,
    }
}

/// Every leaf of the config as `section.key` (arrays of tables as `tasks[i].key`).
fn flatten(config: &Config) -> BTreeMap<String, Value> {
    let mut out = BTreeMap::new();
    let value = serde_json::to_value(config).expect("a config serialises");
    walk(String::new(), value, &mut out);
    out
}

fn walk(prefix: String, value: Value, out: &mut BTreeMap<String, Value>) {
    let join = |key: &str| match prefix.is_empty() {
        true => key.to_string(),
        false => format!("{prefix}.{key}"),
    };
    match value {
        Value::Object(map) => map.into_iter().for_each(|(k, v)| walk(join(&k), v, out)),
        Value::Array(items) if items.iter().any(Value::is_object) => items
            .into_iter()
            .enumerate()
            .for_each(|(i, v)| walk(format!("{prefix}[{i}]"), v, out)),
        leaf => {
            out.insert(prefix, leaf);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn artefact_keys_differ_and_operational_ones_do_not() {
        let old = Config::default();
        let mut new = old.clone();
        new.run.metrics_port = 9000;
        new.run.transitions_per_message = 1024;
        new.tunnel.listen = "tcp/127.0.0.1:7447".into();
        assert!(differing_keys(&old, &new).is_empty());
        // A run saved with `[reproduce]` written out is the same run as one without it.
        let with_reproduce = "[reproduce]\nseeds = 5\nmeta_tasks = 8\n";
        let saved = Config::from_toml_str(with_reproduce, "old.toml", &[]).expect("valid");
        assert!(differing_keys(&saved, &old).is_empty());
        new.collect.policy = "random".into();
        new.tasks[1].lambda = 7.0;
        let keys = differing_keys(&old, &new);
        assert_eq!(keys.len(), 2, "{keys:?}");
        assert!(keys[0].starts_with("collect.policy: "), "{keys:?}");
        assert!(keys[1].starts_with("tasks[1].lambda: "), "{keys:?}");
    }

    fn write_run(dir: &Path, config: &Config) {
        std::fs::create_dir_all(dir).expect("dir");
        std::fs::write(config_file(dir), config.to_toml_string()).expect("config");
    }

    #[test]
    fn another_config_is_refused_naming_the_key_and_fresh_moves_the_run_aside() {
        let tmp = tempfile::tempdir().expect("tmp");
        let dir = tmp.path().join("run");
        let mut old = Config::default();
        old.run.dir = dir.clone();
        assert_eq!(prepare(&old, Reuse::IfSame).expect("a new run"), None);
        let refused = prepare(&old, Reuse::Resume).expect_err("nothing to resume");
        assert!(
            refused.to_string().contains("no run to resume"),
            "{refused}"
        );
        write_run(&dir, &old);
        assert_eq!(prepare(&old, Reuse::Resume).expect("same config"), None);
        let mut new = old.clone();
        new.collect.policy = "random".into();
        for reuse in [Reuse::IfSame, Reuse::Resume] {
            let refused = prepare(&new, reuse)
                .expect_err("another config")
                .to_string();
            assert!(refused.contains("collect.policy"), "{refused}");
            assert!(refused.contains("--fresh"), "{refused}");
        }
        let moved = prepare(&new, Reuse::Fresh)
            .expect("moved")
            .expect("a place");
        assert!(config_file(&moved).exists() && !dir.exists());
    }
}
