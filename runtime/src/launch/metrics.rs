//! The launcher's metrics, built from the names declared in `uavmeta_proto::metrics::launcher`.

use prometheus::{IntCounter, IntCounterVec, IntGauge, Registry};
use uavmeta_proto::metrics::launcher::*;

use crate::metrics::{self, Register};

pub struct LauncherMetrics {
    pub registry: Registry,
    pub restarts: IntCounterVec,
    pub hangs: IntCounterVec,
    pub children_running: IntGauge,
    pub datasets_ready: IntGauge,
    pub checkpoints_announced: IntCounter,
}

impl LauncherMetrics {
    pub fn new() -> Self {
        let registry = metrics::registry(&[]);
        Self {
            restarts: CHILD_RESTARTS.counter_vec(&registry, &["process"]),
            hangs: CHILD_HANGS.counter_vec(&registry, &["process"]),
            children_running: CHILDREN_RUNNING.int_gauge(&registry),
            datasets_ready: DATASETS_READY.int_gauge(&registry),
            checkpoints_announced: CHECKPOINTS_ANNOUNCED.counter(&registry),
            registry,
        }
    }
}
