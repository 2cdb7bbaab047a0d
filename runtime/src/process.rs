//! The start-up every process of a run shares, written once: its iceoryx2 node, the run's
//! service names, its subscription to the run's shutdown announcement and its /metrics endpoint;
//! and the one question its loop asks, whether to stop.
//!
//! ```no_run
//! # fn main() -> Result<(), Box<dyn std::error::Error>> {
//! use std::time::Duration;
//! use uavmeta_proto::config::Config;
//! use uavmeta_runtime::{metrics, process::Process, run_dir::RunDir};
//!
//! let (run, config) = (RunDir::create("runs/example".as_ref())?, Config::default());
//! let process = Process::start(&run, &config, "example")?;
//! let _server = process.serve_metrics(&run, &config, metrics::registry(&[]))?;
//! while !process.stop_requested(Duration::from_millis(100))? {
//!     // One step of the process's work.
//! }
//! # Ok(())
//! # }
//! ```

use std::time::Duration;

use iceoryx2::node::Node;
use iceoryx2::port::subscriber::Subscriber;
use iceoryx2::prelude::*;
use prometheus::Registry;

use uavmeta_proto::config::Config;
use uavmeta_proto::payload::{ServiceNames, Shutdown};

use crate::metrics::{MetricsError, MetricsServer};
use crate::run_dir::RunDir;
use crate::transport::{self, TransportError};
use crate::{domain, liveness};

/// A running process of a run.
pub struct Process {
    /// Its name: of its node (after the run id), port file and metrics snapshot.
    pub name: String,
    pub node: Node<ipc::Service>,
    pub names: ServiceNames,
    /// The run's shutdown announcements (with the service's history, so a process started after
    /// one still sees it).
    pub shutdown: Subscriber<ipc::Service, Shutdown, ()>,
}

impl Process {
    /// Starts process `name` of `run`: its node (`<run id>-<name>`, which also installs the
    /// SIGINT/SIGTERM handler), the run's service names and the shutdown subscription.
    pub fn start(run: &RunDir, config: &Config, name: &str) -> Result<Self, TransportError> {
        let node = domain::node(&format!("{}-{name}", run.id()), &config.run)?;
        let names = run.service_names();
        let shutdown =
            transport::control_subscriber(&transport::shutdown_service(&node, &names, config)?)?;
        Ok(Self {
            name: name.to_string(),
            node,
            names,
            shutdown,
        })
    }

    /// Serves `registry` at /metrics on `run.metrics_host`, on a free port, until the returned
    /// server is dropped. Its port file is what the launcher waits for, so a process calls this
    /// once it is ready to work.
    pub fn serve_metrics(
        &self,
        run: &RunDir,
        config: &Config,
        registry: Registry,
    ) -> Result<MetricsServer, MetricsError> {
        MetricsServer::start(registry, &config.run.metrics_host, 0, run, &self.name)
    }

    /// Waits up to `cycle` for SIGINT/SIGTERM, then reads the shutdown announcements: true if
    /// the process should stop.
    pub fn stop_requested(&self, cycle: Duration) -> Result<bool, TransportError> {
        Ok(!liveness::keep_running(&self.node, cycle)
            || transport::shutdown_requested(&self.shutdown)?)
    }
}
