//! What a run will ask of this machine, estimated from its config before anything starts, and
//! refused, naming the key and the estimate, when the machine cannot hold it: shared memory for
//! every actor's batches (against the free space of /dev/shm), and memory (against
//! `MemAvailable`) for every process and for every size a config sets ([`size_terms`]: replay
//! buffers, datasets, networks, the planner's search).

use uavmeta_proto::config::Config;
use uavmeta_proto::dataset::Transition;
use uavmeta_world::heuristics::PolicySpec;

use super::LaunchError;
use crate::transport;

/// Resident memory of a uavmeta process besides its world's power tables (the binary, libtorch's
/// libraries, iceoryx2, the metrics endpoint): a store of the default world, ready, holds 122 MB
/// (VmRSS, measured 2026-11-25); rounded up for the processes that also train a network.
pub const PROCESS_BASE_BYTES: u64 = 192 << 20;

/// Processes besides the actors: store, meta-learner, evaluator, tunnel, and the launcher itself.
const OTHER_PROCESSES: u64 = 5;

/// What a run needs.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Needs {
    pub actors: u64,
    /// Shared memory of one actor's batches.
    pub shm_per_actor: u64,
    /// Memory of one process: the base and its world's power tables.
    pub memory_per_process: u64,
    /// Memory beyond the base that a size the config sets makes some processes hold, one term
    /// per key ([`size_terms`]).
    pub sizes: Vec<Term>,
}

/// Memory that one key of the config makes `count` processes hold, `bytes` each.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Term {
    /// The key and its value as the config has it, such as `collect.dqn.replay_capacity = 10000`.
    pub key: String,
    /// What the memory holds and where.
    pub what: &'static str,
    pub bytes: u64,
    pub count: u64,
}

impl Term {
    fn total(&self) -> u64 {
        self.bytes.saturating_mul(self.count)
    }
}

impl Needs {
    pub fn of(config: &Config) -> Self {
        let cells = u64::from(config.world.grid_cells).pow(2);
        // Two tables (clear and rain) of one f64 per cell and device.
        let tables = 2 * 8 * cells * config.world.devices as u64;
        let actors = (config.tasks.len() * config.collect.actors_per_task) as u64;
        Self {
            actors,
            shm_per_actor: transport::actor_shared_memory(&config.run),
            memory_per_process: PROCESS_BASE_BYTES + tables,
            sizes: size_terms(config, actors),
        }
    }

    pub fn processes(&self) -> u64 {
        self.actors + OTHER_PROCESSES
    }

    /// Every process's base and tables, and every size term.
    pub fn memory(&self) -> u64 {
        let sizes = self.sizes.iter().map(Term::total);
        sizes.fold(
            self.memory_per_process.saturating_mul(self.processes()),
            u64::saturating_add,
        )
    }
}

/// Bytes one dataset transition takes in memory with `devices` devices: the struct, and its two
/// observation arrays of 2 + K `u16`s on the heap, each with the allocator's 8-byte header,
/// rounded up to its 16-byte granule.
pub fn transition_bytes(devices: usize) -> u64 {
    let array = (2 * (2 + devices) as u64 + 8).div_ceil(16) * 16;
    std::mem::size_of::<Transition>() as u64 + 2 * array
}

/// Bytes a Q-network of `hidden` widths takes while it trains: f32 weights, their gradients,
/// Adam's two moments and a target network, five copies of its parameters.
fn network_bytes(config: &Config, hidden: &[usize]) -> u64 {
    let widths = std::iter::once(config.world.observation_len())
        .chain(hidden.iter().copied())
        .chain(std::iter::once(config.world.action_count()));
    let widths: Vec<u64> = widths.map(|w| w as u64).collect();
    let parameters = widths
        .windows(2)
        .map(|pair| (pair[0] + 1).saturating_mul(pair[1]))
        .fold(0u64, u64::saturating_add);
    parameters.saturating_mul(5 * 4)
}

/// The memory each size a config sets makes its processes hold: the online agents' replay
/// buffers and networks, the datasets the meta-learner loads, the networks it trains, and the
/// planner's search in the launcher.
pub fn size_terms(config: &Config, actors: u64) -> Vec<Term> {
    let (collect, dqn, k) = (&config.collect, &config.collect.dqn, config.world.devices);
    let online = matches!(collect.policy.parse(), Ok(PolicySpec::DqnOnline));
    let online_actors = if online { actors } else { 0 };
    let tasks = config.tasks.len() as u64;
    let transition = transition_bytes(k);
    // A replay buffer reserves its capacity of structs at once and fills the arrays as it goes.
    let struct_bytes = std::mem::size_of::<Transition>() as u64;
    let replay = (dqn.replay_capacity as u64)
        .saturating_mul(struct_bytes)
        .saturating_add(
            (dqn.replay_capacity.min(dqn.steps) as u64).saturating_mul(transition - struct_bytes),
        );
    let datasets = (collect.transitions as u64).saturating_mul(transition);
    let learner = &config.learner;
    vec![
        Term {
            key: format!("collect.dqn.replay_capacity = {}", dqn.replay_capacity),
            what: "the online DQN agent's replay buffer, in each actor",
            bytes: replay,
            count: online_actors,
        },
        Term {
            key: format!("collect.dqn.hidden = {:?}", dqn.hidden),
            what: "the online DQN agent's network while it trains, in each actor",
            bytes: network_bytes(config, &dqn.hidden),
            count: online_actors,
        },
        Term {
            key: format!("collect.transitions = {}", collect.transitions),
            what: "one task's dataset, per task in the meta-learner and per online agent's sample",
            bytes: datasets,
            count: tasks + online_actors,
        },
        Term {
            key: format!("learner.hidden = {:?}", learner.hidden),
            what: "the network the meta-learner trains",
            bytes: network_bytes(config, &learner.hidden),
            count: 1,
        },
        Term {
            key: format!("planner.beam_width = {}", config.planner.beam_width),
            what: "the planner reference's search, in the launcher",
            bytes: u64::try_from(config.planner.memory_bytes(&config.world)).unwrap_or(u64::MAX),
            count: 1,
        },
    ]
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
            "run.transitions_per_message = {} with run.subscriber_buffer = {} needs {} of shared memory per \
             actor, {} for {} actors; /dev/shm has {} free",
            config.run.transitions_per_message,
            config.run.subscriber_buffer,
            gb(needs.shm_per_actor),
            gb(shm),
            needs.actors,
            gb(available.shm_bytes)
        ));
    }
    let memory = needs.memory();
    if memory > available.memory_bytes {
        return refuse(memory_refusal(
            config,
            needs,
            memory,
            available.memory_bytes,
        ));
    }
    Ok(())
}

/// What a run that does not fit the memory available needs, by key, largest first.
fn memory_refusal(config: &Config, needs: &Needs, memory: u64, available: u64) -> String {
    let processes = Term {
        key: format!(
            "world.grid_cells = {} with world.devices = {}",
            config.world.grid_cells, config.world.devices
        ),
        what: "the process and its world's tables, in each process",
        bytes: needs.memory_per_process,
        count: needs.processes(),
    };
    let mut terms: Vec<&Term> = needs.sizes.iter().chain([&processes]).collect();
    terms.sort_by_key(|t| std::cmp::Reverse(t.total()));
    let listed: Vec<String> = terms
        .iter()
        // The terms of at least 1% of the total: the rest changes nothing.
        .filter(|t| t.total() >= memory / 100)
        .map(|t| {
            format!(
                "{}: {} for {} ({} x {})",
                t.key,
                gb(t.total()),
                t.what,
                t.count,
                gb(t.bytes)
            )
        })
        .collect();
    format!(
        "the run needs about {} of memory and this machine has {} available; by key, largest \
         first (those of 1% or more): {} ({} tasks x collect.actors_per_task = {} make {} processes)",
        gb(memory),
        gb(available),
        listed.join("; "),
        config.tasks.len(),
        config.collect.actors_per_task,
        needs.processes()
    )
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
        config.run.transitions_per_message = 16_384;
        let needs = Needs::of(&config);
        let available = Available {
            shm_bytes: 2_000_000_000,
            memory_bytes: 24 << 30,
        };
        let refused = check(&config, &needs, &available)
            .expect_err("too big")
            .to_string();
        assert!(
            refused.contains("run.transitions_per_message = 16384"),
            "{refused}"
        );
        assert!(refused.contains("/dev/shm has 2.0 GB free"), "{refused}");
        config.run.transitions_per_message = 64;
        check(&config, &Needs::of(&config), &available).expect("the default fits");
    }

    #[test]
    fn a_replay_buffer_beyond_memory_is_refused_naming_the_key_the_value_and_the_estimate() {
        let mut config = Config::default();
        config.collect.dqn.replay_capacity = 1_000_000_000;
        let refused = refused_on_24_gib(&config);
        let each = 1e9 * std::mem::size_of::<Transition>() as f64 / 1e9;
        assert!(
            refused.contains("collect.dqn.replay_capacity = 1000000000")
                && refused.contains(&format!("{each:.1} GB")),
            "{refused}"
        );
    }

    #[test]
    fn a_large_world_times_many_processes_is_refused_naming_the_world() {
        let mut config = Config::default();
        config.world.grid_cells = 500;
        config.world.devices = 64;
        config.collect.actors_per_task = 7;
        let refused = refused_on_24_gib(&config);
        assert!(refused.contains("world.grid_cells = 500"), "{refused}");
    }

    /// Why a machine of 12 GiB of /dev/shm and 24 GiB of memory refuses `config`.
    fn refused_on_24_gib(config: &Config) -> String {
        let available = Available {
            shm_bytes: 12 << 30,
            memory_bytes: 24 << 30,
        };
        check(config, &Needs::of(config), &available)
            .expect_err("too much memory")
            .to_string()
    }
}
