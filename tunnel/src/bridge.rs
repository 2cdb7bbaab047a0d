//! The iceoryx2 side of a tunnel: the run's services, held open with uavmeta's settings, and the
//! link that relays them over the Zenoh session.

use std::collections::BTreeSet;
use std::fmt;
use std::time::Instant;

use iceoryx2::node::Node;
use iceoryx2::port::backpressure_strategy::BackpressureStrategy;
use iceoryx2::port::publisher::Publisher;
use iceoryx2::port::subscriber::Subscriber;
use iceoryx2::prelude::*;
use iceoryx2_integrations_zenoh_link_carrier::ZenohCarrier;
use iceoryx2_link::Link;
use iceoryx2_link_tunnel::Tunnel;
use uavmeta_proto::config::Config;
use uavmeta_proto::payload::{Crossing, DatasetReady, ServiceNames, Shutdown, StoreAck};
use uavmeta_runtime::domain;
use uavmeta_runtime::run_dir::RunDir;
use uavmeta_runtime::transport::{self, AckService, ControlService, TransitionService};
use zenoh::Session;

use crate::{TunnelError, DISCOVER_EVERY};

/// The services remote actors use, opened (or created) by the tunnel's process with uavmeta's
/// settings and schema attribute before any link exists. Without them, the link would create a
/// service the other side offers as a mirror with iceoryx2's defaults, which uavmeta's openers
/// then refuse; held open, they are the local side the link exports and relays into.
///
/// Only the services of [`ServiceNames::tunnel_routes`] cross, and each only its way: the
/// transitions of each remote host's own services (`ServiceNames::for_host`) for the tasks
/// `tunnel.hosts` lets it serve, and everything the learner's host alone announces through its
/// `to-remote/` copy, which [`Forwarders`] fill on the learner's host and empty on a remote one.
/// The learner host's tunnel opens every listed host's services, a remote host's its own.
pub(crate) struct RunServices {
    /// Per host, its transition services: the keys its access-control rules let it put on.
    transitions: Vec<(String, Vec<TransitionService>)>,
    acks: Vec<(AckService, AckService)>,
    dataset_ready: (ControlService<DatasetReady>, ControlService<DatasetReady>),
    /// The run's own shutdown service, and its copy that crosses.
    shutdown: (ControlService<Shutdown>, ControlService<Shutdown>),
    /// The names the link may bridge, and no other.
    pub names: BTreeSet<String>,
}

impl RunServices {
    pub fn open(
        node: &Node<ipc::Service>,
        run: &RunDir,
        config: &Config,
    ) -> Result<Self, TunnelError> {
        let names = ServiceNames::new(run.id());
        let crossing = |service: String| names.to_remote(&service);
        let hosts: Vec<&str> = match run.host() {
            Some(host) => vec![host],
            None => config.tunnel.hosts.keys().map(String::as_str).collect(),
        };
        let (mut transitions, mut acks, mut routes) = (Vec::new(), Vec::new(), BTreeSet::new());
        for host in hosts {
            let own = names.for_host(host);
            let tasks = config.tunnel.tasks_of(host, &config.tasks);
            let mut services = Vec::new();
            for t in &tasks {
                services.push(transport::transition_service(
                    node,
                    &own,
                    &t.name,
                    &config.run,
                )?);
                acks.push((
                    transport::ack_service(node, &own, &t.name, &config.run)?,
                    transport::ack_service_at(node, crossing(own.acks(&t.name)), &config.run)?,
                ));
            }
            transitions.push((host.to_string(), services));
            routes.extend(
                own.tunnel_routes(tasks)
                    .into_iter()
                    .map(|(service, way)| match way {
                        Crossing::ToLearner => service,
                        Crossing::ToRemote => crossing(service),
                    }),
            );
        }
        Ok(Self {
            transitions,
            acks,
            dataset_ready: (
                transport::control_service(node, names.dataset_ready(), config)?,
                transport::control_service(node, crossing(names.dataset_ready()), config)?,
            ),
            shutdown: (
                transport::control_service(node, names.shutdown(), config)?,
                transport::control_service(node, crossing(names.shutdown()), config)?,
            ),
            names: routes,
        })
    }

    /// The run's own shutdown service on this host.
    pub fn shutdown(&self) -> &ControlService<Shutdown> {
        &self.shutdown.0
    }

    /// Per host, the iceoryx2 service hashes of its transition services: what its frames cross
    /// the tunnel under (`iox2/v1/channel/<hash>/...`).
    pub fn transition_hashes(&self) -> Vec<(String, Vec<String>)> {
        (self.transitions.iter())
            .map(|(host, services)| {
                let hashes = services
                    .iter()
                    .map(|s| s.service_hash().as_str().to_string());
                (host.clone(), hashes.collect())
            })
            .collect()
    }
}

/// Copies what one service receives into another, by copy (a few bytes each).
struct Forward<T: fmt::Debug + ZeroCopySend + Copy + 'static> {
    from: Subscriber<ipc::Service, T, ()>,
    to: Publisher<ipc::Service, T, ()>,
}

impl<T: fmt::Debug + ZeroCopySend + Copy + 'static> Forward<T> {
    fn pump(&self) -> Result<(), TunnelError> {
        while let Some(sample) = self
            .from
            .receive()
            .map_err(transport::receive_failed("receive what crosses the tunnel"))?
        {
            transport::announce(&self.to, *sample)?;
        }
        Ok(())
    }
}

/// Which way the [`Forwarders`] copy.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Side {
    /// The learner's host: its services into their `to-remote/` copies.
    Learner,
    /// A remote host: the `to-remote/` copies into its own services.
    Remote,
}

/// The copies between a run's services and their `to-remote/` copies that make acknowledgements
/// and announcements one-way: on the learner's host nothing reads a `to-remote/` service, so a
/// remote host that publishes into one reaches no process there.
pub(crate) struct Forwarders {
    acks: Vec<Forward<StoreAck>>,
    dataset_ready: Forward<DatasetReady>,
    shutdown: Forward<Shutdown>,
    /// When a failed copy was last logged: a link coming or going makes a receive fail for a
    /// moment, which must neither stop the tunnel nor flood its log.
    last_warning: std::cell::Cell<Option<Instant>>,
}

impl Forwarders {
    pub fn new(services: &RunServices, side: Side) -> Result<Self, TunnelError> {
        let acks = services
            .acks
            .iter()
            .map(|(own, crossing)| {
                let (from, to) = ordered(own, crossing, side);
                Ok(Forward {
                    from: transport::ack_subscriber(from)?,
                    to: transport::ack_publisher(to)?,
                })
            })
            .collect::<Result<_, TunnelError>>()?;
        Ok(Self {
            acks,
            dataset_ready: control_forward(&services.dataset_ready, side)?,
            shutdown: control_forward(&services.shutdown, side)?,
            last_warning: Default::default(),
        })
    }

    /// Copies everything waiting; a failure is logged (at most every few seconds) and the next
    /// round tries again.
    pub fn pump(&self) {
        let pumped = self
            .acks
            .iter()
            .try_for_each(Forward::pump)
            .and_then(|()| self.dataset_ready.pump())
            .and_then(|()| self.shutdown.pump());
        if let Err(error) = pumped {
            let quiet = self
                .last_warning
                .get()
                .is_some_and(|at| at.elapsed() < DISCOVER_EVERY * 50);
            if !quiet {
                self.last_warning.set(Some(Instant::now()));
                tracing::warn!(%error, "cannot copy what crosses the tunnel; trying again");
            }
        }
    }
}

/// (from, to) of a service and its copy on `side`.
fn ordered<'s, S>(own: &'s S, crossing: &'s S, side: Side) -> (&'s S, &'s S) {
    match side {
        Side::Learner => (own, crossing),
        Side::Remote => (crossing, own),
    }
}

fn control_forward<T: fmt::Debug + ZeroCopySend + Copy + 'static>(
    (own, crossing): &(ControlService<T>, ControlService<T>),
    side: Side,
) -> Result<Forward<T>, TunnelError> {
    let (from, to) = ordered(own, crossing, side);
    Ok(Forward {
        // With history: a remote host that joins late still hears what was announced.
        from: transport::control_subscriber(from)?,
        to: transport::control_publisher(to)?,
    })
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
        let mut iceoryx = domain::iceoryx_config(&config.run)?;
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
