//! The actor's metrics: every name it exports, in one place. The registry labels them all with
//! the actor's task and id.

use std::collections::HashMap;

use prometheus::{Counter, Gauge, Histogram, IntCounter, IntGauge, IntGaugeVec, Opts, Registry};

use uavmeta_learner::metrics::{counter, latency_histogram, register};

use super::Phase;
use crate::dqn_online::{OnlineDqn, RECENT_EPISODES};

pub struct ActorMetrics {
    pub registry: Registry,
    pub steps: IntCounter,
    pub transitions_published: IntCounter,
    pub batches_resent: IntCounter,
    pub store_changes: IntCounter,
    pub transitions_resent: IntCounter,
    pub unacknowledged: IntGauge,
    pub transitions_lost: IntCounter,
    pub batches_published: IntCounter,
    pub episodes: IntCounter,
    pub episode_return: Gauge,
    pub episode_aoi: Gauge,
    pub episode_power: Gauge,
    pub episode_outages: Gauge,
    pub backpressure_wait: Counter,
    pub batch_duration: Histogram,
    /// `actor_phase{phase}`: 1 for the phase the actor is in, 0 for the others.
    phase: IntGaugeVec,
}

/// The online DQN agent's training, exported by `dqn-online` actors only (another policy has no
/// exploration rate or training returns to report, and a 0 would read as one).
pub struct OnlineDqnMetrics {
    epsilon: Gauge,
    recent_return: Gauge,
}

impl OnlineDqnMetrics {
    pub fn new(registry: &Registry) -> Self {
        let gauge = |name: &str, help: &str| {
            register(
                registry,
                Gauge::with_opts(Opts::new(name, help)).expect("valid gauge"),
            )
        };
        let metrics = Self {
            epsilon: gauge("actor_online_dqn_epsilon", "Exploration rate of the online DQN agent's epsilon-greedy policy."),
            recent_return: gauge("actor_online_dqn_recent_return", &format!("Mean return of the online DQN agent's last {RECENT_EPISODES} finished training episodes.")),
        };
        // No sample (NaN) until the first episode ends, rather than a made-up 0.
        metrics.recent_return.set(f64::NAN);
        metrics
    }

    /// The agent's figures after a block of training steps.
    pub fn observe(&self, agent: &OnlineDqn) {
        self.epsilon.set(agent.epsilon());
        if let Some(recent) = agent.recent_return() {
            self.recent_return.set(recent);
        }
    }
}

impl ActorMetrics {
    pub fn new(task: &str, actor: u32) -> Self {
        let labels = HashMap::from([
            ("task".to_string(), task.to_string()),
            ("actor".to_string(), format!("{actor:08x}")),
        ]);
        let registry = Registry::new_custom(Some("uavmeta".into()), Some(labels))
            .expect("valid prefix and labels");
        let gauge = |name: &str, help: &str| {
            register(
                &registry,
                Gauge::with_opts(Opts::new(name, help)).expect("valid gauge"),
            )
        };
        Self {
            steps: counter(&registry, "actor_steps_total", "Environment steps taken (for dqn-online, training steps included)."),
            transitions_published: counter(&registry, "actor_transitions_published_total", "Transitions delivered to the store's service, each counted once."),
            batches_resent: counter(&registry, "actor_batches_resent_total", "Batches sent again because iceoryx2 reported them delivered to no store."),
            store_changes: counter(&registry, "actor_store_changes_total", "Times a new store replaced the one the actor sent to, so the actor sent again what that store had not acknowledged."),
            transitions_resent: counter(&registry, "actor_transitions_resent_total", "Transitions delivered again to a store that replaced the one they went to (not in transitions_published)."),
            unacknowledged: register(
                &registry,
                IntGauge::with_opts(Opts::new(
                    "actor_transitions_unacknowledged",
                    "Transitions sent but not yet acknowledged as appended by the store, which the actor keeps to send again.",
                ))
                .expect("valid gauge"),
            ),
            transitions_lost: counter(&registry, "actor_transitions_lost_total", "Transitions delivered to no store because the store went away during the send and run.keep_until_stored is off; the restarted store counts them as missing."),
            batches_published: counter(&registry, "actor_batches_published_total", "Batches sent to the store's service."),
            episodes: counter(&registry, "actor_episodes_total", "Episodes finished by the behaviour policy."),
            episode_return: gauge("actor_episode_return", "Return of the last finished episode."),
            episode_aoi: gauge("actor_episode_aoi", "Mean AoI over steps and devices of the last finished episode."),
            episode_power: gauge("actor_episode_power_watts", "Mean transmit power per step of the last finished episode, in watts."),
            episode_outages: gauge("actor_episode_outages", "Steps in outage of the last finished episode."),
            backpressure_wait: register(
                &registry,
                Counter::with_opts(Opts::new(
                    "actor_backpressure_wait_seconds_total",
                    "Time blocked because the store's buffer was full or no store was connected.",
                ))
                .expect("valid counter"),
            ),
            batch_duration: latency_histogram(&registry, "actor_batch_duration_seconds", "Time to roll out and send one batch."),
            phase: register(
                &registry,
                IntGaugeVec::new(
                    Opts::new("actor_phase", "1 for what the actor is doing: training (its online DQN agent), sending (transitions to the store), sent (all of them, waiting for the store)."),
                    &["phase"],
                )
                .expect("valid gauge"),
            ),
            registry,
        }
    }

    /// Marks `phase` as the actor's phase.
    pub fn set_phase(&self, phase: Phase) {
        for p in Phase::ALL {
            self.phase
                .with_label_values(&[p.name()])
                .set((p == phase) as i64);
        }
    }
}
