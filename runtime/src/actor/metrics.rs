//! The actor's metrics, built from the names declared in `uavmeta_proto::metrics::actor`. The
//! registry labels them all with the actor's task and id.

use prometheus::{Counter, Gauge, Histogram, IntCounter, IntGauge, IntGaugeVec, Registry};

use uavmeta_actors::policy::dqn_online::OnlineDqn;
use uavmeta_proto::metrics::actor::*;
use uavmeta_proto::stats::EpisodeMetrics;

use super::Phase;
use crate::metrics::{self, Register};

pub struct ActorMetrics {
    pub registry: Registry,
    pub steps: IntCounter,
    pub transitions_published: IntCounter,
    pub batches_resent: IntCounter,
    pub store_changes: IntCounter,
    pub transitions_resent: IntCounter,
    pub unacknowledged: IntGauge,
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
        let metrics = Self {
            epsilon: ONLINE_DQN_EPSILON.gauge(registry),
            recent_return: ONLINE_DQN_RECENT_RETURN.gauge(registry),
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
        let registry = metrics::registry(&[("task", task), ("actor", &format!("{actor:08x}"))]);
        Self {
            steps: STEPS.counter(&registry),
            transitions_published: TRANSITIONS_PUBLISHED.counter(&registry),
            batches_resent: BATCHES_RESENT.counter(&registry),
            store_changes: STORE_CHANGES.counter(&registry),
            transitions_resent: TRANSITIONS_RESENT.counter(&registry),
            unacknowledged: TRANSITIONS_UNACKNOWLEDGED.int_gauge(&registry),
            batches_published: BATCHES_PUBLISHED.counter(&registry),
            episodes: EPISODES.counter(&registry),
            episode_return: EPISODE_RETURN.gauge(&registry),
            episode_aoi: EPISODE_AOI.gauge(&registry),
            episode_power: EPISODE_POWER.gauge(&registry),
            episode_outages: EPISODE_OUTAGES.gauge(&registry),
            backpressure_wait: BACKPRESSURE_WAIT.seconds_counter(&registry),
            batch_duration: BATCH_DURATION.latency_histogram(&registry),
            phase: PHASE.int_gauge_vec(&registry, &["phase"]),
            registry,
        }
    }

    /// The figures of a finished episode of the behaviour policy.
    pub fn observe_episode(&self, episode: &EpisodeMetrics) {
        self.episodes.inc();
        self.episode_return.set(episode.ret);
        self.episode_aoi.set(episode.aoi);
        self.episode_power.set(episode.power_mw * 1e-3);
        self.episode_outages.set(episode.outages as f64);
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

#[cfg(test)]
mod tests {
    use uavmeta_actors::policy::dqn_online::RECENT_EPISODES;

    #[test]
    fn the_recent_return_help_names_the_agents_window() {
        let help = super::ONLINE_DQN_RECENT_RETURN.help;
        assert!(
            help.contains(&format!(" last {RECENT_EPISODES} ")),
            "{help}"
        );
    }
}
