//! Keys that were removed or renamed. A config that still names one is refused with what became
//! of it (the new key, or why it went and where the finding is), rather than with serde's bare
//! "unknown field"; a saved config of an older version fails the same way.

use super::ConfigError;

/// What became of a key.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Fate {
    /// Gone with its code; the reason and where the finding is recorded.
    Removed(&'static str),
    /// The same setting under another key.
    Renamed(&'static str),
}

/// Every key that no longer exists, dotted as in a file; a `tasks.` key applies to every task.
#[rustfmt::skip]
pub const MOVED: &[(&str, Fate)] = &[
    ("collect.dqn_steps", Fate::Renamed("collect.dqn.steps")),
    ("collect.replay_capacity", Fate::Renamed("collect.dqn.replay_capacity")),
    ("collect.learning_starts", Fate::Renamed("collect.dqn.learning_starts")),
    ("collect.train_every", Fate::Renamed("collect.dqn.train_every")),
    ("collect.eps_start", Fate::Renamed("collect.dqn.eps_start")),
    ("collect.eps_end", Fate::Renamed("collect.dqn.eps_end")),
    ("collect.eps_decay_steps", Fate::Renamed("collect.dqn.eps_decay_steps")),
    ("collect.dqn_hidden", Fate::Renamed("collect.dqn.hidden")),
    ("collect.dqn_lr", Fate::Renamed("collect.dqn.lr")),
    ("collect.dqn_lr_final_fraction", Fate::Renamed("collect.dqn.lr_final_fraction")),
    ("collect.dqn_double", Fate::Renamed("collect.dqn.double_dqn")),
    ("collect.dqn_huber", Fate::Renamed("collect.dqn.huber")),
    ("collect.dqn_grad_clip_norm", Fate::Renamed("collect.dqn.grad_clip_norm")),
    ("collect.dqn_target_update_every", Fate::Renamed("collect.dqn.target_update_every")),
    ("collect.dqn_select_every", Fate::Renamed("collect.dqn.select_every")),
    ("meta.shots", Fate::Renamed("meta.support_batch_size")),
    ("meta.support_shots", Fate::Renamed("meta.support_batch_size")),
    ("meta.query_shots", Fate::Renamed("meta.query_batch_size")),
    ("context.context_shots", Fate::Renamed("context.transitions_per_context")),
    ("meta.w0_average_decay", Fate::Renamed("meta.average_decay_per_outer_step")),
    ("meta.average_decay", Fate::Renamed("meta.average_decay_per_outer_step")),
    ("meta.target_update_every", Fate::Renamed("meta.target_update_meta_epochs")),
    ("learner.fqe_steps", Fate::Removed(FQE)),
    ("learner.fqe_target_update_every", Fate::Removed(FQE)),
    ("learner.fqe_lr", Fate::Removed(FQE)),
    ("learner.fqe_alpha", Fate::Removed(FQE)),
    ("learner.init_penalty", Fate::Removed("L2-SP toward the init did not hold on held-out tasks (docs/EXPERIMENTS.md, D5)")),
    ("meta.eta_outer_final_fraction", Fate::Removed("a falling meta step size did no better than a constant one (docs/EXPERIMENTS.md, C7 and C13)")),
    ("collect.dqn_n_step", Fate::Removed("n-step returns trapped the agents on start cells here (docs/EXPERIMENTS.md, A3)")),
    ("learner.population", Fate::Removed(STACKING)),
    ("collect.population", Fate::Removed(STACKING)),
    ("meta.population", Fate::Removed(STACKING)),
    ("run.device", Fate::Removed(STACKING)),
    ("run.control_buffer", Fate::Removed("the announcements a control subscriber buffers and a late joiner receives are a constant of the transport (256)")),
    ("run.keep_until_stored", Fate::Removed("an actor always keeps its batches until the store acknowledges them; keeping them only until the store is proven connected saved 3 ns a transition (docs/EXPERIMENTS.md, T1)")),
    ("run.batch_size", Fate::Renamed("run.transitions_per_message")),
    ("learner.batch", Fate::Renamed("learner.batch_size")),
    ("learner.select_every", Fate::Removed("a run's network was picked by its return in a world fitted to the shots and scored from the evaluation's start cells, which on lambda tasks is the evaluation itself; every algorithm reports its last epoch (docs/EXPERIMENTS.md, D24)")),
    ("collect.sample_newest", Fate::Removed("shots from the newest part of the buffer did worse than from all of it (docs/EXPERIMENTS.md, B and B4)")),
];

/// Why the lockstep populations went, with `run.device` that placed them.
const STACKING: &str = "training stacked networks in lockstep gave no speed-up on CPU and every \
     run is one network on the CPU (docs/EXPERIMENTS.md, S1)";

const FQE: &str =
    "the fitted-Q-evaluation selection did not rank this world's policies (docs/EXPERIMENTS.md, D4)";

/// The first key of [`MOVED`] that `doc` (a config file with its overrides applied) still sets.
pub(super) fn check(doc: &toml_edit::DocumentMut, origin: &str) -> Result<(), ConfigError> {
    for (key, fate) in MOVED {
        let (section, name) = key.split_once('.').expect("a moved key is dotted");
        if sets(doc.get(section), name) {
            return Err(ConfigError::Moved {
                origin: origin.to_string(),
                key: key.to_string(),
                fate: *fate,
            });
        }
    }
    Ok(())
}

/// Whether `section` (a table, or an array of tables such as `[[tasks]]`) sets `name`.
fn sets(section: Option<&toml_edit::Item>, name: &str) -> bool {
    match section {
        Some(toml_edit::Item::ArrayOfTables(tables)) => tables.iter().any(|t| t.contains_key(name)),
        Some(item) => item.as_table_like().is_some_and(|t| t.contains_key(name)),
        None => false,
    }
}

impl std::fmt::Display for Fate {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Fate::Removed(why) => write!(f, "was removed ({why}): delete it"),
            Fate::Renamed(new) => write!(f, "was renamed: write `{new}` instead"),
        }
    }
}
