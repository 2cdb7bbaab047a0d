//! The store's metrics, built from the names declared in `uavmeta_proto::metrics::store`.

use prometheus::{Histogram, IntCounterVec, IntGaugeVec, Registry};
use uavmeta_proto::metrics::store::*;

use crate::metrics::{self, Register};

pub struct StoreMetrics {
    pub registry: Registry,
    pub batches_received: IntCounterVec,
    pub transitions_received: IntCounterVec,
    pub transitions_stored: IntCounterVec,
    pub transitions_dropped: IntCounterVec,
    pub transitions_rejected: IntCounterVec,
    pub transitions_missing: IntCounterVec,
    pub dataset_transitions: IntGaugeVec,
    pub dataset_ready: IntGaugeVec,
    pub batch_latency: Histogram,
    pub append_duration: Histogram,
}

impl StoreMetrics {
    pub fn new() -> Self {
        let registry = metrics::registry(&[]);
        let task = ["task"];
        Self {
            batches_received: BATCHES_RECEIVED.counter_vec(&registry, &task),
            transitions_received: TRANSITIONS_RECEIVED.counter_vec(&registry, &task),
            transitions_stored: TRANSITIONS_STORED.counter_vec(&registry, &task),
            transitions_dropped: TRANSITIONS_DROPPED.counter_vec(&registry, &["task", "reason"]),
            transitions_rejected: TRANSITIONS_REJECTED
                .counter_vec(&registry, &["task", "actor", "reason"]),
            transitions_missing: TRANSITIONS_MISSING.counter_vec(&registry, &task),
            dataset_transitions: DATASET_TRANSITIONS.int_gauge_vec(&registry, &task),
            dataset_ready: DATASET_READY.int_gauge_vec(&registry, &task),
            batch_latency: BATCH_LATENCY.latency_histogram(&registry),
            append_duration: APPEND_DURATION.latency_histogram(&registry),
            registry,
        }
    }
}
