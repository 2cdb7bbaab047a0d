//! The evaluator's metrics, built from the names declared in `uavmeta_proto::metrics::evaluator`.

use prometheus::{GaugeVec, Histogram, IntCounter, Registry};
use uavmeta_proto::metrics::{self, evaluator::*};

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
}
