//! Every metric a uavmeta process exports, named and described once.
//!
//! The names are part of the contract between processes: the launcher reads the store's, the
//! Grafana dashboard (`docs/grafana/uavmeta.json`) queries them all, and the end-to-end tests
//! assert on them. So each is declared here once, as a [`Metric`] constant in the module of the
//! process kind that exports it ([`actor`], [`evaluator`], [`store`], [`meta_learner`],
//! [`launcher`]); a process builds its registry from these constants in the `metrics` module
//! beside its loop (`uavmeta_runtime::metrics::Register`), and a reader passes the same constant
//! to `uavmeta_runtime::metrics::sum`, so a renamed metric is a compile error everywhere rather
//! than a series that silently stops. The /metrics endpoint that serves them is
//! `uavmeta_runtime::metrics`.
//!
//! Naming (Prometheus conventions, checked by `promtool check metrics` in the end-to-end tests and
//! by this module's tests): every name starts with `uavmeta_`, then the process kind, then what is
//! measured, in base units (`_seconds`, `_watts`), with `_total` on counters and only on them.
//! The age of information has no SI unit: the world counts it in time steps (slots), so its
//! gauges end in `_steps`. Latencies are histograms; label values come from small fixed sets (task
//! names, method names, process names, reasons).

/// What a metric is, which fixes the suffix its name may carry.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Kind {
    /// Only ever increases; the name ends in `_total`.
    Counter,
    /// Goes up and down; the name does not end in `_total`.
    Gauge,
    /// A latency distribution; the name ends in `_seconds`.
    Histogram,
}

/// One exported metric: its full name (with the `uavmeta_` prefix), its help text and its kind.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Metric {
    pub name: &'static str,
    pub help: &'static str,
    pub kind: Kind,
}

/// Declares a process kind's metrics as [`Metric`] constants, and `ALL`, the list of them.
macro_rules! declare {
    ($($(#[$doc:meta])* $id:ident: $kind:ident $name:literal, $help:literal;)*) => {
        $($(#[$doc])* pub const $id: Metric = Metric {
            name: concat!("uavmeta_", $name),
            help: $help,
            kind: Kind::$kind,
        };)*
        /// Every metric of this process kind.
        pub const ALL: &[Metric] = &[$($id),*];
    };
}

/// An actor's metrics; its registry labels every one with its `task` and `actor` id.
pub mod actor {
    use super::{Kind, Metric};
    declare! {
        STEPS: Counter "actor_steps_total", "Environment steps taken (for dqn-online, training steps included).";
        TRANSITIONS_PUBLISHED: Counter "actor_transitions_published_total", "Transitions delivered to the store's service, each counted once.";
        BATCHES_RESENT: Counter "actor_batches_resent_total", "Batches sent again because iceoryx2 reported them delivered to no store.";
        STORE_CHANGES: Counter "actor_store_changes_total", "Times a new store replaced the one the actor sent to, so the actor sent again what that store had not acknowledged.";
        TRANSITIONS_RESENT: Counter "actor_transitions_resent_total", "Transitions delivered again to a store that replaced the one they went to (not in transitions_published).";
        TRANSITIONS_UNACKNOWLEDGED: Gauge "actor_transitions_unacknowledged", "Transitions sent but not yet acknowledged as appended by the store, which the actor keeps to send again.";
        BATCHES_PUBLISHED: Counter "actor_batches_published_total", "Batches sent to the store's service.";
        EPISODES: Counter "actor_episodes_total", "Episodes finished by the behaviour policy.";
        EPISODE_RETURN: Gauge "actor_episode_return", "Return of the last finished episode.";
        EPISODE_AOI: Gauge "actor_episode_aoi_steps", "Mean AoI over steps and devices of the last finished episode, in time steps.";
        EPISODE_POWER: Gauge "actor_episode_power_watts", "Mean transmit power per step of the last finished episode, in watts.";
        EPISODE_OUTAGES: Gauge "actor_episode_outages", "Steps in outage of the last finished episode.";
        BACKPRESSURE_WAIT: Counter "actor_backpressure_wait_seconds_total", "Time blocked because the store's buffer was full or no store was connected.";
        BATCH_DURATION: Histogram "actor_batch_duration_seconds", "Time to roll out and send one batch.";
        /// Labelled by `phase` (`uavmeta_runtime::actor::Phase`).
        PHASE: Gauge "actor_phase", "1 for what the actor is doing: training (its online DQN agent), sending (transitions to the store), sent (all of them, waiting for the store).";
        /// Exported by `dqn-online` actors only: another policy has no exploration rate to report,
        /// and a 0 would read as one.
        ONLINE_DQN_EPSILON: Gauge "actor_online_dqn_epsilon", "Exploration rate of the online DQN agent's epsilon-greedy policy.";
        /// The window is `uavmeta_actors::policy::dqn_online::RECENT_EPISODES` (a test there
        /// checks that this text names it).
        ONLINE_DQN_RECENT_RETURN: Gauge "actor_online_dqn_recent_return", "Mean return of the online DQN agent's last 20 finished training episodes.";
    }
}

/// The dataset store's metrics, labelled by `task`.
pub mod store {
    use super::{Kind, Metric};
    declare! {
        BATCHES_RECEIVED: Counter "store_batches_received_total", "Batches received from actors.";
        TRANSITIONS_RECEIVED: Counter "store_transitions_received_total", "Transitions received from actors.";
        TRANSITIONS_STORED: Counter "store_transitions_stored_total", "Transitions appended to the dataset file by this store process.";
        /// Labelled by `reason` too, one of [`DROPPED_REASONS`].
        TRANSITIONS_DROPPED: Counter "store_transitions_dropped_total", "Received transitions not stored: duplicate (sequence number already stored), surplus (the dataset was complete), foreign (another run, world or schema), invalid (the batch failed validation; see store_transitions_rejected_total).";
        /// Labelled by `actor` and `reason` too, one of [`REJECTION_REASONS`]; actors beyond
        /// [`REJECTION_ACTORS`] distinct ids share the actor label [`OTHER_ACTORS`].
        TRANSITIONS_REJECTED: Counter "store_transitions_rejected_total", "Transitions of batches dropped whole because one transition failed validation, by actor and by the check it failed: non_finite, action, position, aoi, step, reward, next_state (the world gives another), sequence_window (numbered far ahead of what the actor has stored).";
        TRANSITIONS_MISSING: Counter "store_transitions_missing_total", "Sequence numbers skipped by an actor's batches: transitions lost in transit, counted from the dataset file on start.";
        DATASET_TRANSITIONS: Gauge "store_dataset_transitions", "Transitions in the task's dataset file.";
        DATASET_READY: Gauge "store_dataset_ready", "1 once the task's dataset holds collect.transitions and is announced.";
        BATCH_LATENCY: Histogram "store_batch_latency_seconds", "Time from an actor's send to the store's receive of a batch.";
        APPEND_DURATION: Histogram "store_append_duration_seconds", "Time to append and flush one batch to its dataset file.";
    }

    /// `reason`: the sequence number is already stored.
    pub const DUPLICATE: &str = "duplicate";
    /// `reason`: the task's dataset was already complete.
    pub const SURPLUS: &str = "surplus";
    /// `reason`: from another run, world or schema.
    pub const FOREIGN: &str = "foreign";
    /// `reason`: the batch failed validation ([`TRANSITIONS_REJECTED`] says which check).
    pub const INVALID: &str = "invalid";
    /// Why a received transition was not stored: the `reason` label's fixed set.
    pub const DROPPED_REASONS: [&str; 4] = [DUPLICATE, SURPLUS, FOREIGN, INVALID];

    /// Rejection `reason`: a reward that is NaN or infinite.
    pub const NON_FINITE: &str = "non_finite";
    /// Rejection `reason`: an action not below 5K.
    pub const ACTION: &str = "action";
    /// Rejection `reason`: a cell off the grid, or not the world's fixed start cell at step 0.
    pub const POSITION: &str = "position";
    /// Rejection `reason`: an AoI outside [1, aoi_max], or above what the step index allows.
    pub const AOI: &str = "aoi";
    /// Rejection `reason`: a step index at or past the horizon, or a truncation flag that
    /// disagrees with it.
    pub const STEP: &str = "step";
    /// Rejection `reason`: the reward is not what the world gives for (s, a).
    pub const REWARD: &str = "reward";
    /// Rejection `reason`: s(t+1) is not what the world gives for (s, a).
    pub const NEXT_STATE: &str = "next_state";
    /// Rejection `reason`: a first sequence number far ahead of what the actor has stored.
    pub const SEQUENCE_WINDOW: &str = "sequence_window";
    /// The rejection `reason` label's fixed set.
    pub const REJECTION_REASONS: [&str; 8] = [
        NON_FINITE,
        ACTION,
        POSITION,
        AOI,
        STEP,
        REWARD,
        NEXT_STATE,
        SEQUENCE_WINDOW,
    ];
    /// Distinct actor ids the rejection counter labels by their own id; the label set stays
    /// small whatever ids a hostile publisher makes up.
    pub const REJECTION_ACTORS: usize = 256;
    /// The `actor` label of rejections from actors beyond [`REJECTION_ACTORS`].
    pub const OTHER_ACTORS: &str = "other";
}

/// The evaluator's metrics; its gauges are labelled by `task` and `method`.
pub mod evaluator {
    use super::{Kind, Metric};
    declare! {
        RETURN: Gauge "evaluator_return", "Mean episode return of the latest evaluated checkpoint.";
        AOI: Gauge "evaluator_aoi_steps", "Mean AoI over steps and devices of the latest evaluated checkpoint, in time steps.";
        POWER: Gauge "evaluator_power_watts", "Mean transmit power per step of the latest evaluated checkpoint, in watts.";
        OUTAGES: Gauge "evaluator_outages", "Mean steps in outage per episode of the latest evaluated checkpoint.";
        EPOCH: Gauge "evaluator_epoch", "Training epochs (meta-epochs for maml-init) behind the latest evaluated checkpoint.";
        CHECKPOINTS_EVALUATED: Counter "evaluator_checkpoints_evaluated_total", "Checkpoints evaluated.";
        EVALUATION_DURATION: Histogram "evaluator_evaluation_duration_seconds", "Time to load and evaluate one checkpoint.";
    }
}

/// The meta-learner's metrics.
pub mod meta_learner {
    use super::{Kind, Metric};
    declare! {
        META_EPOCH: Gauge "meta_learner_meta_epoch", "Meta-epochs behind w0.";
        META_LOSS: Gauge "meta_learner_meta_loss", "Meta-loss (sum of the adapted weights' query losses) of the last meta-epoch.";
        META_EPOCH_DURATION: Histogram "meta_learner_meta_epoch_duration_seconds", "Time of one meta-epoch.";
        CHECKPOINTS_WRITTEN: Counter "meta_learner_checkpoints_written_total", "Checkpoints written and announced.";
        FINE_TUNE_EPOCHS: Counter "meta_learner_fine_tune_epochs_total", "Meta-test fine-tuning epochs run.";
    }
}

/// The launcher's metrics; the per-child counters are labelled by `process`.
pub mod launcher {
    use super::{Kind, Metric};
    declare! {
        CHILD_RESTARTS: Counter "launcher_child_restarts_total", "Restarts of a crashed child process.";
        CHILD_HANGS: Counter "launcher_child_hangs_total", "Children killed because their heartbeat stopped (run.hang_timeout_seconds).";
        CHILDREN_RUNNING: Gauge "launcher_children_running", "Child processes running.";
        DATASETS_READY: Gauge "launcher_datasets_ready", "Tasks whose dataset the store announced complete.";
        CHECKPOINTS_ANNOUNCED: Counter "launcher_checkpoints_announced_total", "Checkpoints the meta-learner announced.";
    }
}

/// Every metric of every process kind.
pub fn all() -> impl Iterator<Item = Metric> {
    [
        actor::ALL,
        store::ALL,
        evaluator::ALL,
        meta_learner::ALL,
        launcher::ALL,
    ]
    .into_iter()
    .flatten()
    .copied()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_follow_the_conventions_and_are_distinct() {
        let mut names = std::collections::BTreeSet::new();
        for metric in all() {
            let name = metric.name;
            assert!(names.insert(name), "{name} is declared twice");
            assert!(name.starts_with("uavmeta_"), "{name}");
            assert!(
                name.chars()
                    .all(|c| c.is_ascii_lowercase() || c.is_ascii_digit() || c == '_'),
                "{name}"
            );
            assert_eq!(
                name.ends_with("_total"),
                metric.kind == Kind::Counter,
                "{name}"
            );
            if metric.kind == Kind::Histogram {
                assert!(name.ends_with("_seconds"), "{name}");
            }
            assert!(metric.help.ends_with('.'), "{name}: {}", metric.help);
        }
    }
}
