//! The evaluator's metrics, built from the names declared in `uavmeta_proto::metrics::evaluator`.

use std::time::Duration;

use prometheus::{GaugeVec, Histogram, IntCounter, Registry};
use uavmeta_proto::metrics::evaluator::*;

use super::EvaluationRow;

use crate::metrics::{self, Register};

pub struct EvaluatorMetrics {
    pub registry: Registry,
    pub ret: GaugeVec,
    pub aoi: GaugeVec,
    pub power: GaugeVec,
    pub outages: GaugeVec,
    pub epoch: GaugeVec,
    pub evaluated: IntCounter,
    pub duration: Histogram,
}

impl EvaluatorMetrics {
    pub fn new() -> Self {
        let registry = metrics::registry(&[]);
        let labels = ["task", "method"];
        Self {
            ret: RETURN.gauge_vec(&registry, &labels),
            aoi: AOI.gauge_vec(&registry, &labels),
            power: POWER.gauge_vec(&registry, &labels),
            outages: OUTAGES.gauge_vec(&registry, &labels),
            epoch: EPOCH.gauge_vec(&registry, &labels),
            evaluated: CHECKPOINTS_EVALUATED.counter(&registry),
            duration: EVALUATION_DURATION.latency_histogram(&registry),
            registry,
        }
    }

    /// One evaluated checkpoint's figures, which took `duration` to load and evaluate.
    pub fn observe(&self, row: &EvaluationRow, duration: Duration) {
        let (labels, p) = ([row.task.as_str(), row.method.as_str()], &row.policy);
        self.ret.with_label_values(&labels).set(p.ret.mean);
        self.aoi.with_label_values(&labels).set(p.aoi.mean);
        self.power
            .with_label_values(&labels)
            .set(p.power_mw.mean * 1e-3);
        self.outages.with_label_values(&labels).set(p.outages.mean);
        self.epoch.with_label_values(&labels).set(row.epoch as f64);
        self.evaluated.inc();
        self.duration.observe(duration.as_secs_f64());
    }
}
