//! What a run will ask of this machine, estimated from its config before anything starts, and
//! refused, naming the key and the estimate, when the machine cannot hold it: shared memory for
//! every actor's batches (against the free space of /dev/shm), memory for every process (against
//! `MemAvailable`), and the number of processes.

use uavmeta_proto::config::Config;

use super::LaunchError;
use crate::transport;

/// Resident memory of a uavmeta process besides its world's power tables (the binary, libtorch's
/// libraries, iceoryx2, the metrics endpoint): a store of the default world, ready, holds 122 MB
/// (VmRSS, measured 2026-11-25); rounded up for the processes that also train a network.
pub const PROCESS_BASE_BYTES: u64 = 192 << 20;

/// Processes besides the actors: store, meta-learner, evaluator, tunnel, and the launcher itself.
const OTHER_PROCESSES: u64 = 5;

/// What a run needs.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Needs {
    pub actors: u64,
    /// Shared memory of one actor's batches.
    pub shm_per_actor: u64,
    /// Memory of one process: the base and its world's power tables.
    pub memory_per_process: u64,
}

impl Needs {
    pub fn of(config: &Config) -> Self {
        let cells = u64::from(config.world.grid_cells).pow(2);
        // Two tables (clear and rain) of one f64 per cell and device.
        let tables = 2 * 8 * cells * config.world.devices as u64;
        Self {
            actors: (config.tasks.len() * config.collect.actors_per_task) as u64,
            shm_per_actor: transport::actor_shared_memory(&config.run),
            memory_per_process: PROCESS_BASE_BYTES + tables,
        }
    }

    pub fn processes(&self) -> u64 {
        self.actors + OTHER_PROCESSES
    }
}

/// What this machine has free now.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Available {
    pub shm_bytes: u64,
    pub memory_bytes: u64,
}

impl Available {
    /// Free space of /dev/shm and `MemAvailable` of /proc/meminfo; `None` where unreadable.
    pub fn here() -> Option<Self> {
        Some(Self {
            shm_bytes: free_bytes("/dev/shm")?,
            memory_bytes: mem_available()?,
        })
    }
}

/// Refuses `needs` beyond `available`, naming the key behind the estimate.
pub fn check(config: &Config, needs: &Needs, available: &Available) -> Result<(), LaunchError> {
    let refuse = |message: String| Err(LaunchError::Resources { message });
    let shm = needs.shm_per_actor * needs.actors;
    if shm > available.shm_bytes {
        return refuse(format!(
            "run.batch_size = {} with run.subscriber_buffer = {} needs {} of shared memory per \
             actor, {} for {} actors; /dev/shm has {} free",
            config.run.batch_size,
            config.run.subscriber_buffer,
            gb(needs.shm_per_actor),
            gb(shm),
            needs.actors,
            gb(available.shm_bytes)
        ));
    }
    let memory = needs.memory_per_process * needs.processes();
    if memory > available.memory_bytes {
        return refuse(format!(
            "world.grid_cells = {} with world.devices = {} needs about {} per process, and \
             {} tasks x collect.actors_per_task = {} make {} processes: {} in all; this machine \
             has {} available",
            config.world.grid_cells,
            config.world.devices,
            gb(needs.memory_per_process),
            config.tasks.len(),
            config.collect.actors_per_task,
            needs.processes(),
            gb(memory),
            gb(available.memory_bytes)
        ));
    }
    Ok(())
}

/// Checks the run against this machine, if the machine says what it has.
pub fn check_here(config: &Config) -> Result<(), LaunchError> {
    match Available::here() {
        Some(available) => check(config, &Needs::of(config), &available),
        None => {
            tracing::warn!(
                "cannot read /dev/shm's free space or MemAvailable; resources unchecked"
            );
            Ok(())
        }
    }
}

fn gb(bytes: u64) -> String {
    format!("{:.1} GB", bytes as f64 / 1e9)
}

fn free_bytes(path: &str) -> Option<u64> {
    let path = std::ffi::CString::new(path).ok()?;
    // SAFETY: statvfs writes the struct it is given; the path is a valid C string.
    let stat = unsafe {
        let mut stat = std::mem::zeroed::<libc::statvfs>();
        (libc::statvfs(path.as_ptr(), &mut stat) == 0).then_some(stat)?
    };
    Some(stat.f_bavail as u64 * stat.f_frsize as u64)
}

fn mem_available() -> Option<u64> {
    let text = std::fs::read_to_string("/proc/meminfo").ok()?;
    let line = text.lines().find(|l| l.starts_with("MemAvailable:"))?;
    let kib: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kib * 1024)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_huge_batch_is_refused_naming_the_key_and_both_figures() {
        let mut config = Config::default();
        config.run.batch_size = 16_384;
        let needs = Needs::of(&config);
        let available = Available {
            shm_bytes: 2_000_000_000,
            memory_bytes: 24 << 30,
        };
        let refused = check(&config, &needs, &available)
            .expect_err("too big")
            .to_string();
        assert!(refused.contains("run.batch_size = 16384"), "{refused}");
        assert!(refused.contains("/dev/shm has 2.0 GB free"), "{refused}");
        config.run.batch_size = 64;
        check(&config, &Needs::of(&config), &available).expect("the default fits");
    }

    #[test]
    fn a_large_world_times_many_processes_is_refused_naming_the_world() {
        let mut config = Config::default();
        config.world.grid_cells = 500;
        config.world.devices = 64;
        config.collect.actors_per_task = 7;
        let available = Available {
            shm_bytes: 12 << 30,
            memory_bytes: 24 << 30,
        };
        let refused = check(&config, &Needs::of(&config), &available)
            .expect_err("too much memory")
            .to_string();
        assert!(refused.contains("world.grid_cells = 500"), "{refused}");
    }
}
