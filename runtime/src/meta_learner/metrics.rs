//! The meta-learner's metrics, built from the names declared in
//! `uavmeta_proto::metrics::meta_learner`.

use prometheus::{Gauge, Histogram, IntCounter, IntGauge, Registry};
use uavmeta_proto::metrics::meta_learner::*;

use crate::metrics::{self, Register};

pub struct MetaLearnerMetrics {
    pub registry: Registry,
    pub meta_epoch: IntGauge,
    pub meta_loss: Gauge,
    pub meta_epoch_duration: Histogram,
    pub checkpoints: IntCounter,
    pub fine_tune_epochs: IntCounter,
}

impl MetaLearnerMetrics {
    pub fn new() -> Self {
        let registry = metrics::registry(&[]);
        Self {
            meta_epoch: META_EPOCH.int_gauge(&registry),
            meta_loss: META_LOSS.gauge(&registry),
            meta_epoch_duration: META_EPOCH_DURATION.latency_histogram(&registry),
            checkpoints: CHECKPOINTS_WRITTEN.counter(&registry),
            fine_tune_epochs: FINE_TUNE_EPOCHS.counter(&registry),
            registry,
        }
    }
}
