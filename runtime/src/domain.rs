//! An iceoryx2 domain (`run.domain`): its config, the node of a process in it, and the removal of
//! what dead processes left in it (their ports, and the segments and service files a process
//! killed mid-creation leaves unfinished), on the caller's thread or on a [`Cleaner`]'s.

use std::path::PathBuf;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::Duration;

use iceoryx2::node::Node;
use iceoryx2::prelude::*;
use uavmeta_proto::config::RunConfig;

use crate::run_dir::FileError;
use crate::transport::{service_error, TransportError};

/// The iceoryx2 config of `run.domain`: iceoryx2's defaults, with the domain's own prefix and
/// root path, so that nodes, services and shared memory of two domains never meet. This is how
/// iceoryx2's own examples and tests isolate systems on one machine.
pub fn iceoryx_config(run: &RunConfig) -> Result<iceoryx2::config::Config, TransportError> {
    let mut config = iceoryx2::config::Config::global_config().clone();
    if run.domain.is_empty() {
        return Ok(config);
    }
    let invalid = |message: String| TransportError::ServiceName {
        name: run.domain.clone(),
        message,
    };
    let prefix = format!("iox2_{}_", run.domain);
    config.global.prefix = iceoryx2::prelude::FileName::new(prefix.as_bytes())
        .map_err(|e| invalid(format!("run.domain as an iceoryx2 prefix: {e:?}")))?;
    let root = format!("/tmp/iceoryx2/{}/", run.domain);
    let root = iceoryx2::prelude::Path::new(root.as_bytes())
        .map_err(|e| invalid(format!("run.domain as an iceoryx2 root path: {e:?}")))?;
    config.global.set_root_path(&root);
    Ok(config)
}

/// Removes what iceoryx2 keeps of `run.domain` after its last process has gone: the domain's
/// global management segment in /dev/shm and its root directory. For a domain made for one test
/// or benchmark, once none of its processes runs; the default domain (empty) is left alone.
pub fn remove_domain(run: &RunConfig) -> Result<(), TransportError> {
    if run.domain.is_empty() {
        return Ok(());
    }
    let config = iceoryx_config(run)?;
    let gone = |path: &std::path::Path, removed: std::io::Result<()>| match removed {
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(()),
        removed => removed.map_err(FileError::at(path, "remove")),
    };
    let root = PathBuf::from(config.global.root_path().to_string());
    gone(&root, std::fs::remove_dir_all(&root))?;
    let prefix = config.global.prefix.to_string();
    for entry in std::fs::read_dir("/dev/shm")
        .into_iter()
        .flatten()
        .flatten()
    {
        if entry.file_name().to_string_lossy().starts_with(&prefix) {
            gone(&entry.path(), std::fs::remove_file(entry.path()))?;
        }
    }
    Ok(())
}

/// The iceoryx2 node of a process in `run.domain`, named after the process so `iox2 node list`
/// shows who is who.
pub fn node(process: &str, run: &RunConfig) -> Result<Node<ipc::Service>, TransportError> {
    // iceoryx2 warns on every start that it runs on its built-in defaults, which uavmeta means
    // to; its own errors still show (IOX2_LOG_LEVEL overrides).
    set_log_level_from_env_or(LogLevel::Error);
    let action = "create the node";
    let name =
        NodeName::new(process).map_err(|e| service_error(process, action)(format!("{e:?}")))?;
    let config = iceoryx_config(run)?;
    // Creating a node sweeps dead nodes' resources.
    remove_unfinished(&config);
    let node = NodeBuilder::new()
        .name(&name)
        .config(&config)
        .create::<ipc::Service>()
        .map_err(service_error(process, action))?;
    // The first wait registers iceoryx2's SIGINT/SIGTERM handler, so a termination request that
    // arrives while a publisher is blocked on backpressure is seen by `termination_requested`.
    let _ = node.wait(Duration::ZERO);
    Ok(node)
}

/// Removes the resources of dead processes from every service (their ports would otherwise block
/// the living on full buffers); the number of dead nodes cleaned up.
pub fn cleanup_dead_nodes(node: &Node<ipc::Service>) -> u64 {
    remove_unfinished(node.config());
    node.try_cleanup_dead_nodes().cleanups
}

/// A leftover younger than this may be a creation in progress (that takes microseconds); an older
/// one is what a killed process left.
const UNFINISHED_AGE: Duration = Duration::from_secs(10);

/// Longest that [`remove_unfinished`] waits in all, however many leftovers it meets: a file that
/// keeps being made unfinished again (by another user: iceoryx2's files are world-writable) would
/// otherwise stay young, and waited for, for ever.
const UNFINISHED_BOUND: Duration = Duration::from_secs(12);

/// The permission iceoryx2's file-based static storage (a service's static config) keeps while
/// its creator writes it; the creator makes it read-only once complete.
const UNFINISHED_SERVICE_FILE_MODE: u32 = 0o600;

/// Removes what a process killed in the middle of creating something in the domain leaves
/// unfinished, which iceoryx2 0.10 takes for a creation in progress for ever:
/// - a shared-memory segment at size zero (killed between creating and sizing it): the dead-node
///   sweep waits on it without a timeout (`posix_shared_memory::open_impl` on
///   `MappingSizeIsZero`), so every later sweep in the domain would hang;
/// - a service's static config file still writable: every later open of that service fails with
///   `HangsInCreation`, so a store killed at that moment could not be restarted.
///
/// A leftover younger than [`UNFINISHED_AGE`] may be a creation in progress, or what a process
/// killed a moment ago left before its successor started (both found by the chaos test), so it is
/// waited for: finished, gone, or old enough to remove, all within [`UNFINISHED_BOUND`], after
/// which what is left is given up on with a warning. The wait beats the heartbeat, so a restarted
/// child that waits here is not taken for hung.
fn remove_unfinished(config: &iceoryx2::config::Config) {
    let prefix = config.global.prefix.to_string();
    let service_dir = PathBuf::from(config.global.service_dir().to_string());
    let places: [(PathBuf, Unfinished); 2] = [
        (service_dir, is_unfinished_service_file),
        ("/dev/shm".into(), is_unfinished_segment),
    ];
    let leftovers: Vec<(PathBuf, Unfinished)> = places
        .iter()
        .flat_map(|(dir, unfinished)| {
            let entries = std::fs::read_dir(dir).into_iter().flatten().flatten();
            entries
                .filter(|e| e.file_name().to_string_lossy().starts_with(&prefix))
                .map(|e| e.path())
                .filter(|path| unfinished(path))
                .map(|path| (path, *unfinished))
        })
        .collect();
    let start = std::time::Instant::now();
    for (path, unfinished) in leftovers {
        if !wait_for_leftover(&path, unfinished, start) {
            return;
        }
    }
}

/// Whether a file is what a creator leaves before it finishes (false once gone).
type Unfinished = fn(&std::path::Path) -> bool;

/// Waits while `path` is unfinished, removing it once older than [`UNFINISHED_AGE`]; false if
/// the sweep that began at `start` has passed [`UNFINISHED_BOUND`] and gives up.
fn wait_for_leftover(
    path: &std::path::Path,
    unfinished: Unfinished,
    start: std::time::Instant,
) -> bool {
    while unfinished(path) {
        let age = (std::fs::metadata(path).and_then(|m| m.modified()).ok())
            .and_then(|at| at.elapsed().ok());
        if age.is_some_and(|age| age > UNFINISHED_AGE) {
            if std::fs::remove_file(path).is_ok() {
                tracing::warn!(path = %path.display(), "removed an iceoryx2 file a killed process left unfinished");
            }
            return true;
        }
        if start.elapsed() > UNFINISHED_BOUND {
            tracing::warn!(path = %path.display(), waited = ?start.elapsed(), "gave up on an iceoryx2 file that stays unfinished (made so again and again?)");
            return false;
        }
        crate::liveness::heartbeat();
        std::thread::sleep(Duration::from_millis(50));
    }
    true
}

/// A shared-memory segment not yet sized (false once gone).
fn is_unfinished_segment(path: &std::path::Path) -> bool {
    std::fs::metadata(path).is_ok_and(|m| m.is_file() && m.len() == 0)
}

/// A service's static config file still writable, as while its creator writes it (false once
/// gone).
fn is_unfinished_service_file(path: &std::path::Path) -> bool {
    use std::os::unix::fs::PermissionsExt;
    std::fs::metadata(path).is_ok_and(|m| {
        m.is_file() && m.permissions().mode() & 0o777 == UNFINISHED_SERVICE_FILE_MODE
    })
}

/// Sweeps for dead processes' iceoryx2 resources on a thread of its own, with a node of its own,
/// so that a sweep that waits (on a segment left unfinished, or one another user truncates) never
/// stops the loop that asked for it. [`Cleaner::request`] returns a ticket at once;
/// [`Cleaner::finished`] tells when a sweep that started after it has ended.
pub struct Cleaner {
    shared: Arc<CleanerState>,
}

#[derive(Default)]
struct CleanerState {
    /// Sweeps requested so far, and whether the owner has gone.
    requested: std::sync::Mutex<(u64, bool)>,
    wake: std::sync::Condvar,
    /// Requests served: every ticket up to this one has had a whole sweep after it.
    done: AtomicU64,
}

impl Cleaner {
    /// Starts the thread; its node is `<process>-cleaner` in `run.domain`.
    pub fn start(process: &str, run: &RunConfig) -> Self {
        let shared = Arc::new(CleanerState::default());
        let state = Arc::clone(&shared);
        let (name, run) = (format!("{process}-cleaner"), run.clone());
        let spawned = std::thread::Builder::new()
            .name("iceoryx2-cleaner".into())
            .spawn(move || state.serve(&name, &run));
        if let Err(error) = spawned {
            tracing::warn!(%error, "cannot start the iceoryx2 cleaner thread; dead processes' resources stay");
        }
        Self { shared }
    }

    /// Asks for a sweep; returns its ticket.
    pub fn request(&self) -> u64 {
        let mut requested = self.shared.lock();
        requested.0 += 1;
        self.shared.wake.notify_one();
        requested.0
    }

    /// Whether a sweep has ended since `ticket` was requested.
    pub fn finished(&self, ticket: u64) -> bool {
        self.shared.done.load(Ordering::Acquire) >= ticket
    }

    /// Asks for a sweep and waits for it, at most `bound`; whether it ended in time.
    pub fn sweep_within(&self, bound: Duration) -> bool {
        let ticket = self.request();
        let start = std::time::Instant::now();
        while !self.finished(ticket) {
            if start.elapsed() > bound {
                tracing::warn!(
                    ?bound,
                    "the iceoryx2 clean-up did not finish in time; going on without it"
                );
                return false;
            }
            std::thread::sleep(Duration::from_millis(10));
        }
        true
    }
}

impl Drop for Cleaner {
    fn drop(&mut self) {
        self.shared.lock().1 = true;
        self.shared.wake.notify_one();
    }
}

impl CleanerState {
    fn lock(&self) -> std::sync::MutexGuard<'_, (u64, bool)> {
        self.requested.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// The thread: one sweep per wake-up that found new requests, until the owner goes.
    fn serve(&self, name: &str, run: &RunConfig) {
        let node = match node(name, run) {
            Ok(node) => node,
            Err(error) => {
                tracing::warn!(%error, "the iceoryx2 cleaner has no node; dead processes' resources stay");
                return;
            }
        };
        loop {
            let ticket = {
                let mut requested = self.lock();
                while requested.0 == self.done.load(Ordering::Acquire) && !requested.1 {
                    requested = self.wake.wait(requested).unwrap_or_else(|e| e.into_inner());
                }
                if requested.1 {
                    return;
                }
                requested.0
            };
            let cleaned = cleanup_dead_nodes(&node);
            if cleaned > 0 {
                tracing::info!(cleaned, "removed iceoryx2 resources of dead processes");
            }
            self.done.store(ticket, Ordering::Release);
        }
    }
}
