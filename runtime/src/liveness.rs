//! Whether a process should go on: the termination request (SIGINT, SIGTERM) iceoryx2's handler
//! records, and the heartbeat by which a launched process tells the launcher it is making
//! progress.

use std::path::Path;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, SystemTime};

use iceoryx2::node::{Node, NodeWaitFailure};
use iceoryx2::prelude::*;
use iceoryx2_bb_posix::signal::SignalHandler;

/// Set once a termination request was seen: iceoryx2's signal state forgets a signal once read.
static TERMINATING: AtomicBool = AtomicBool::new(false);

/// True once SIGINT or SIGTERM arrived (iceoryx2's handler records it), for good.
pub fn termination_requested() -> bool {
    if TERMINATING.load(Ordering::Relaxed) {
        return true;
    }
    let requested = SignalHandler::termination_requested();
    if requested {
        TERMINATING.store(true, Ordering::Relaxed);
    }
    requested
}

/// Sleeps `cycle` on `node`; false once the process should stop. `Node::wait` also fails when any
/// other signal iceoryx2 catches (SIGCONT after a stop, SIGURG, ...) interrupts its sleep, which is
/// no reason to end a process, so only a termination request counts.
pub fn keep_running(node: &Node<ipc::Service>, cycle: Duration) -> bool {
    heartbeat();
    match node.wait(cycle) {
        Err(NodeWaitFailure::TerminationRequest) => {
            TERMINATING.store(true, Ordering::Relaxed);
            false
        }
        _ => !termination_requested(),
    }
}

/// The variable through which the launcher tells a child which file to beat on.
pub const HEARTBEAT_FILE_ENV: &str = "UAVMETA_HEARTBEAT_FILE";

/// At most this often a beat touches the file; the launcher's `run.hang_timeout_seconds` is many
/// times longer.
const HEARTBEAT_EVERY: Duration = Duration::from_millis(500);

/// Tells the launcher that this process's loop is making progress, by moving the modification
/// time of the file named in [`HEARTBEAT_FILE_ENV`]. A stopped, deadlocked or livelocked process
/// stops moving it, and the launcher kills and restarts it. Every loop that polls its node beats
/// through [`keep_running`]; a long computation calls this between its steps (training, through
/// the `uavmeta_learner::progress::OnStep` the meta-learner passes it). A process started by hand
/// has no such file, and beats go nowhere.
pub fn heartbeat() {
    struct Beat {
        file: std::fs::File,
        last: std::sync::Mutex<Option<std::time::Instant>>,
    }
    static BEAT: std::sync::OnceLock<Option<Beat>> = std::sync::OnceLock::new();
    let beat = BEAT.get_or_init(|| {
        let path = std::env::var_os(HEARTBEAT_FILE_ENV)?;
        match std::fs::OpenOptions::new().write(true).create(true).truncate(false).open(&path) {
            Ok(file) => Some(Beat {
                file,
                last: std::sync::Mutex::new(None),
            }),
            Err(e) => {
                tracing::warn!(path = %Path::new(&path).display(), error = %e, "cannot open the heartbeat file; the launcher will take this process for hung");
                None
            }
        }
    });
    let Some(beat) = beat else { return };
    let mut last = beat.last.lock().unwrap_or_else(|e| e.into_inner());
    if last.is_none_or(|at| at.elapsed() >= HEARTBEAT_EVERY) {
        // A failed touch looks like a missed beat; the next one tries again.
        let _ = beat.file.set_modified(SystemTime::now());
        *last = Some(std::time::Instant::now());
    }
}
