//! The iceoryx2 side of a tunnel: the run's services, held open with uavmeta's settings, and the
//! link that relays them over the Zenoh session.

use std::collections::BTreeSet;
use std::time::Instant;

use iceoryx2::node::Node;
use iceoryx2::port::backpressure_strategy::BackpressureStrategy;
use iceoryx2::prelude::*;
use iceoryx2_integrations_zenoh_link_carrier::ZenohCarrier;
use iceoryx2_link::Link;
use iceoryx2_link_tunnel::Tunnel;
use uavmeta_proto::config::Config;
use uavmeta_proto::transport::{self, AckService, ControlService, RunDir, ServiceNames};
use uavmeta_proto::transport::{DatasetReady, Shutdown, TransitionService};
use zenoh::Session;

use crate::{TunnelError, DISCOVER_EVERY};

/// The services a remote actor uses, opened (or created) by the tunnel's process with uavmeta's
/// settings and schema attribute before any link exists. Without them, the link would create a
/// service the other side offers as a mirror with iceoryx2's defaults, which uavmeta's openers
/// then refuse; held open, they are the local side the link exports and relays into.
pub(crate) struct RunServices {
    _transitions: Vec<TransitionService>,
    _acks: Vec<AckService>,
    _dataset_ready: ControlService<DatasetReady>,
    pub shutdown: ControlService<Shutdown>,
    /// The names the link may bridge, and no other.
    pub names: BTreeSet<String>,
}

impl RunServices {
    pub fn open(
        node: &Node<ipc::Service>,
        run: &RunDir,
        config: &Config,
    ) -> Result<Self, TunnelError> {
        let names = ServiceNames::new(run);
        let tasks = &config.tasks;
        Ok(Self {
            _transitions: tasks
                .iter()
                .map(|t| transport::transition_service(node, &names, &t.name, &config.run))
                .collect::<Result<_, _>>()?,
            _acks: tasks
                .iter()
                .map(|t| transport::ack_service(node, &names, &t.name, &config.run))
                .collect::<Result<_, _>>()?,
            _dataset_ready: transport::dataset_ready_service(node, &names, config)?,
            shutdown: transport::shutdown_service(node, &names, config)?,
            names: names.remote_actor_services(tasks).into_iter().collect(),
        })
    }
}

/// A link relaying the run's services over a Zenoh session.
pub(crate) struct Bridge {
    link: Link<ipc::Service, Tunnel<ZenohCarrier>>,
    last_discovery: Option<Instant>,
}

impl Bridge {
    /// A link with a node of its own (named `process`), so that its ports come and go with it.
    pub fn new(
        process: &str,
        config: &Config,
        session: &Session,
        services: &RunServices,
    ) -> Result<Self, TunnelError> {
        let link_error = |action| move |e: String| TunnelError::Link { action, message: e };
        let mut iceoryx = transport::iceoryx_config(&config.run)?;
        // The link publishes what arrives from the other side into the local service, whose
        // subscribers include its own (drained only between rounds): waiting on a full one, as
        // uavmeta's actors do, deadlocks the link while frames keep arriving (seen in
        // tests/remote.rs). So its publishers skip a full subscriber; a store that falls behind
        // misses that batch and counts the gap.
        iceoryx.defaults.publish_subscribe.backpressure_strategy =
            BackpressureStrategy::DiscardData;
        let name =
            NodeName::new(process).map_err(|e| link_error("name its node")(format!("{e:?}")))?;
        let node = NodeBuilder::new()
            .name(&name)
            .config(&iceoryx)
            .create::<ipc::Service>()
            .map_err(|e| link_error("create its node")(e.to_string()))?;
        let carrier = ZenohCarrier::open(session.clone())
            .map_err(|e| link_error("open the Zenoh carrier")(e.to_string()))?;
        let allowed = services.names.clone();
        let link = Link::new(node, Tunnel::new(carrier, &iceoryx))
            .with_filter(move |name: &ServiceName| allowed.contains(name.as_str()));
        Ok(Self {
            link,
            last_discovery: None,
        })
    }

    /// One round: discovery every [`DISCOVER_EVERY`], then whatever is pending either way.
    pub fn relay(&mut self) {
        if self
            .last_discovery
            .is_none_or(|at| at.elapsed() >= DISCOVER_EVERY)
        {
            self.last_discovery = Some(Instant::now());
            if let Err(error) = self.link.discover() {
                tracing::warn!(%error, "tunnel discovery failed");
            }
        }
        if let Err(error) = self.link.propagate() {
            tracing::warn!(%error, "tunnel relaying failed");
        }
    }
}
