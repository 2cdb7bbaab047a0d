//! What a config will make a process allocate, estimated before anything is allocated, and
//! refused, naming the key, its value, the bytes and what is available, when the process may
//! not hold it (issue #85). Every subcommand, the launch and the Python package call the one
//! check, [`check_memory`], with the [`Job`] they are about to do; where a run writes, they also
//! call [`check_disk`].
//!
//! The memory a process may use is the smaller of `MemAvailable` and what its cgroup's
//! `memory.max` leaves; the environment variable [`MEMORY_ENV`] replaces both (and [`DISK_ENV`]
//! the free space of a disk), so that a test gets the same answer on any machine.

use std::path::{Path, PathBuf};

use crate::config::{Config, TaskConfig, WorldConfig};
use crate::dataset::Transition;
use crate::layout::Layout;

/// Replaces the memory available to the process, in bytes.
pub const MEMORY_ENV: &str = "UAVMETA_MEMORY_BYTES";
/// Replaces the free space of every disk a run writes to, in bytes.
pub const DISK_ENV: &str = "UAVMETA_DISK_BYTES";

/// Resident memory of a uavmeta process besides its world's power tables (the binary, libtorch's
/// libraries, iceoryx2, the metrics endpoint): a store of the default world, ready, holds 122 MB
/// (VmRSS, measured 2026-11-25); rounded up for the processes that also train a network.
pub const PROCESS_BASE_BYTES: u64 = 192 << 20;

/// Processes of a launch besides the actors: store, meta-learner, evaluator, tunnel, and the
/// launcher itself.
const OTHER_PROCESSES: u64 = 5;

/// What a process is about to do with a config: which of its sizes it allocates.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Job {
    /// `uavmeta collect`, and one actor of a run: a behaviour policy (the online DQN agent) and a
    /// dataset written.
    Collect,
    /// `uavmeta train` and `meta-test`: a network trained on shots, evaluated every epoch.
    Train,
    /// `uavmeta meta-train` (MAML or the context learner) and a run's meta-learner: every
    /// meta-train task's dataset, then fine-tuning.
    MetaTrain,
    /// `uavmeta eval`, `env rollout` and a run's evaluator: a policy evaluated.
    Eval,
    /// `uavmeta env rollout --policy planner`: the planner reference's search.
    Plan,
    /// A run's store: the process and its world.
    Store,
    /// `uavmeta launch`: every process of the run on this host, and the planner reference.
    Launch,
    /// The Python package's vector env of `worlds` worlds (0 for one env), or where `evaluation`
    /// an evaluation of that many (with `learner.eval_episodes` the episodes it evaluates), with
    /// the planner reference's search where `planner`.
    Python {
        worlds: u64,
        evaluation: bool,
        planner: bool,
    },
}

/// Memory that one key of the config makes `count` processes (or worlds) hold, `bytes` each.
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
    pub fn total(&self) -> u64 {
        self.bytes.saturating_mul(self.count)
    }
}

/// What a job needs of memory: each process's base and world, and every size term.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Needs {
    pub job: Job,
    pub processes: u64,
    pub sizes: Vec<Term>,
}

impl Needs {
    pub fn of(config: &Config, job: Job) -> Self {
        let processes = match job {
            Job::Launch => actors(config) + OTHER_PROCESSES,
            _ => 1,
        };
        let mut sizes = vec![process_term(config, job, processes)];
        sizes.extend(size_terms(config, job));
        sizes.retain(|t| t.count > 0);
        Self {
            job,
            processes,
            sizes,
        }
    }

    pub fn memory(&self) -> u64 {
        self.sizes
            .iter()
            .map(Term::total)
            .fold(0, u64::saturating_add)
    }
}

fn actors(config: &Config) -> u64 {
    (config.tasks.len() as u64).saturating_mul(config.collect.actors_per_task as u64)
}

/// A world's power tables: two (clear and rain) of one f64 per cell and device.
fn world_table_bytes(w: &WorldConfig) -> u64 {
    (2 * 8 * u64::from(w.grid_cells).pow(2)).saturating_mul(w.devices as u64)
}

/// One evaluated episode's table of visited steps and its states.
fn episode_bytes(w: &WorldConfig) -> u64 {
    u64::from(w.horizon).saturating_mul(24 + 2 * w.layout().observation_len() as u64 + 48)
}

/// Every process's base and its world's tables; in Python, no process base but each world's.
fn process_term(config: &Config, job: Job, processes: u64) -> Term {
    let tables = world_table_bytes(&config.world);
    let key = format!(
        "world.grid_cells = {} with world.devices = {}",
        config.world.grid_cells, config.world.devices
    );
    match job {
        Job::Python { worlds, .. } => Term {
            key,
            what: "each world's power tables",
            bytes: tables,
            count: worlds.max(1),
        },
        _ => Term {
            key,
            what: "the process and its world's tables, in each process",
            bytes: PROCESS_BASE_BYTES + tables,
            count: processes,
        },
    }
}

/// Bytes one dataset transition takes in memory with `devices` devices: the struct, and its two
/// observation arrays of 2 + K `u16`s on the heap, each with the allocator's 8-byte header,
/// rounded up to its 16-byte granule.
pub fn transition_bytes(devices: usize) -> u64 {
    let array = (2 * Layout::new(devices).observation_len() as u64 + 8).div_ceil(16) * 16;
    std::mem::size_of::<Transition>() as u64 + 2 * array
}

/// The most bytes one transition takes in a dataset file with `devices` devices: postcard's
/// varints at their longest (5 bytes a u32, 10 a u64, 3 a u16 and a length), and the f32 and
/// bool as they are.
pub fn transition_file_bytes(devices: usize) -> u64 {
    let observation = 3 + 3 * Layout::new(devices).observation_len() as u64;
    5 + 5 + 10 + 5 + 10 + 3 + 4 + 1 + 2 * observation
}

/// Parameters of a Q-network of `hidden` widths between the observation and the actions.
fn parameters(inputs: usize, hidden: &[usize], outputs: usize) -> u64 {
    let widths: Vec<u64> = std::iter::once(inputs)
        .chain(hidden.iter().copied())
        .chain(std::iter::once(outputs))
        .map(|w| w as u64)
        .collect();
    widths
        .windows(2)
        .map(|pair| (pair[0] + 1).saturating_mul(pair[1]))
        .fold(0u64, u64::saturating_add)
}

/// Bytes a network of `parameters` takes while it trains: f32 weights, their gradients, Adam's
/// two moments and a target network, five copies of its parameters.
fn training_bytes(parameters: u64) -> u64 {
    parameters.saturating_mul(5 * 4)
}

/// Bytes of one batch of `rows` through a network of `hidden` widths: each row's observation and
/// next observation, and every layer's activations for the online and the target network, kept
/// with their gradients for the backward pass (four f32 per activation).
fn batch_bytes(config: &Config, hidden: &[usize], rows: usize) -> u64 {
    let w = &config.world;
    let widths = hidden
        .iter()
        .fold(w.layout().action_count() as u64, |s, &h| {
            s.saturating_add(h as u64)
        });
    let per_row =
        (2 * w.layout().observation_len() as u64 + 4).saturating_add(widths.saturating_mul(4));
    (rows as u64).saturating_mul(per_row).saturating_mul(4)
}

/// How many of `job`'s processes hold one part of the run.
#[derive(Clone, Copy)]
struct Holders {
    online_agent: u64,
    datasets: u64,
    learner: u64,
    /// MAML's batches, per task.
    meta: u64,
    context: u64,
    evaluation: u64,
    planner: u64,
}

impl Holders {
    fn of(config: &Config, job: Job) -> Self {
        let online = config.collect.policy == "dqn-online";
        let online_actors = if online { actors(config) } else { 0 };
        let tasks = config.tasks.len() as u64;
        let none = Self {
            online_agent: 0,
            datasets: 0,
            learner: 0,
            meta: 0,
            context: 0,
            evaluation: 0,
            planner: 0,
        };
        match job {
            Job::Collect => Self {
                online_agent: u64::from(online),
                evaluation: u64::from(online),
                planner: u64::from(config.collect.policy == "planner"),
                ..none
            },
            Job::Train => Self {
                learner: 1,
                evaluation: 1,
                ..none
            },
            Job::MetaTrain => Self {
                datasets: tasks,
                learner: 1,
                meta: 1,
                context: 1,
                evaluation: 1,
                ..none
            },
            Job::Eval => Self {
                learner: 1,
                evaluation: 1,
                ..none
            },
            Job::Plan => Self { planner: 1, ..none },
            Job::Store => none,
            Job::Launch => Self {
                online_agent: online_actors,
                // Per task in the meta-learner, and per online agent's sample.
                datasets: tasks + online_actors,
                learner: 2,
                meta: 1,
                context: 1,
                // The evaluator, the meta-learner and each online agent's selection.
                evaluation: 2 + online_actors,
                planner: 1,
            },
            Job::Python {
                evaluation,
                planner,
                ..
            } => Self {
                evaluation: u64::from(evaluation),
                planner: u64::from(planner),
                ..none
            },
        }
    }
}

/// The memory each size a config sets makes `job`'s processes hold: the online agents' replay
/// buffers and networks, datasets, the networks trained and their batches, the model rows, the
/// evaluation's episode tables, and the planner's search.
pub fn size_terms(config: &Config, job: Job) -> Vec<Term> {
    let holders = Holders::of(config, job);
    let (collect, dqn, w) = (&config.collect, &config.collect.dqn, &config.world);
    let (learner, meta, context) = (&config.learner, &config.meta, &config.context);
    let (obs, actions) = (w.layout().observation_len(), w.layout().action_count());
    let transition = transition_bytes(w.devices);
    // A replay buffer reserves its capacity of structs at once and fills the arrays as it goes.
    let struct_bytes = std::mem::size_of::<Transition>() as u64;
    let replay = (dqn.replay_capacity as u64)
        .saturating_mul(struct_bytes)
        .saturating_add(
            (dqn.replay_capacity.min(dqn.steps) as u64).saturating_mul(transition - struct_bytes),
        );
    let dqn_network = training_bytes(parameters(obs, &dqn.hidden, actions));
    let network = training_bytes(parameters(obs, &learner.hidden, actions));
    let meta_rows = (meta
        .support_batch_size
        .saturating_add(meta.query_batch_size))
    .saturating_mul(meta.inner_steps.saturating_add(1));
    let encoder = parameters(2 * obs + 2, &context.encoder_hidden, context.latent);
    let conditioned = parameters(obs + context.latent, &learner.hidden, actions);
    // Each evaluated episode's table of visited steps and its states, over the exact
    // evaluation's start cells or the episodes asked for, whichever is more.
    let episodes = (learner.eval_episodes as u64).max(u64::from(w.grid_cells).pow(2));
    let evaluation = episodes.saturating_mul(episode_bytes(w));
    let planner = u64::try_from(config.planner.memory_bytes(w)).unwrap_or(u64::MAX);
    vec![
        Term {
            key: format!("collect.dqn.replay_capacity = {}", dqn.replay_capacity),
            what: "the online DQN agent's replay buffer",
            bytes: replay,
            count: holders.online_agent,
        },
        Term {
            key: format!("collect.dqn.hidden = {:?}", dqn.hidden),
            what: "the online DQN agent's network while it trains",
            bytes: dqn_network,
            count: holders.online_agent,
        },
        Term {
            key: format!("collect.dqn.hidden = {:?}", dqn.hidden),
            what: "the online DQN agent's batch of learner.batch_size",
            bytes: batch_bytes(config, &dqn.hidden, learner.batch_size),
            count: holders.online_agent,
        },
        Term {
            key: format!("collect.transitions = {}", collect.transitions),
            what: "one task's dataset in memory",
            bytes: (collect.transitions as u64).saturating_mul(transition),
            count: holders.datasets,
        },
        Term {
            key: format!("learner.hidden = {:?}", learner.hidden),
            what: "the learner's network while it trains",
            bytes: network,
            count: holders.learner,
        },
        Term {
            key: format!("learner.batch_size = {}", learner.batch_size),
            what: "the learner's batch through its network",
            bytes: batch_bytes(config, &learner.hidden, learner.batch_size),
            count: holders.learner,
        },
        Term {
            key: format!("learner.model_rows = {}", learner.model_rows),
            what: "the model rows an epoch adds to the shots",
            bytes: (learner.model_rows as u64)
                .saturating_mul(transition)
                .saturating_add(batch_bytes(config, &learner.hidden, learner.model_rows)),
            count: holders.learner,
        },
        Term {
            key: format!(
                "meta.support_batch_size = {} with meta.query_batch_size = {} and meta.inner_steps = {}",
                meta.support_batch_size, meta.query_batch_size, meta.inner_steps
            ),
            what: "one task's MAML batches, kept through the inner steps",
            bytes: batch_bytes(config, &learner.hidden, meta_rows),
            count: holders.meta.saturating_mul(config.tasks.len() as u64),
        },
        Term {
            key: format!(
                "context.encoder_hidden = {:?} with context.latent = {}",
                context.encoder_hidden, context.latent
            ),
            what: "the context learner's encoder and conditioned network while they train",
            bytes: training_bytes(encoder.saturating_add(conditioned)),
            count: holders.context,
        },
        Term {
            key: format!("context.transitions_per_context = {}", context.transitions_per_context),
            what: "the context learner's batch of contexts",
            bytes: batch_bytes(config, &context.encoder_hidden, context.transitions_per_context)
                .saturating_mul(config.tasks.len() as u64),
            count: holders.context,
        },
        Term {
            key: format!(
                "learner.eval_episodes = {} with world.horizon = {}",
                learner.eval_episodes, w.horizon
            ),
            what: "the evaluation's table of every episode's steps",
            bytes: evaluation,
            count: holders.evaluation,
        },
        Term {
            key: format!("planner.beam_width = {}", config.planner.beam_width),
            what: "the planner reference's search",
            bytes: planner,
            count: holders.planner,
        },
    ]
}

/// A config that asks more of this machine than it has.
#[derive(Debug, thiserror::Error)]
pub enum ResourceError {
    #[error("{origin}: {message}")]
    Memory { origin: String, message: String },
    #[error("{origin}: {message}")]
    Disk { origin: String, message: String },
    #[error("environment variable {name} = {value:?}: expected a number of bytes")]
    Env { name: &'static str, value: String },
}

/// Memory the process may use, and where the figure comes from.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Available {
    pub bytes: u64,
    pub from: String,
}

impl Available {
    /// [`MEMORY_ENV`] if set; otherwise the smaller of `MemAvailable` and what the cgroup's
    /// `memory.max` leaves; `None` where neither can be read.
    pub fn memory() -> Result<Option<Self>, ResourceError> {
        if let Some(bytes) = from_env(MEMORY_ENV)? {
            return Ok(Some(Self {
                bytes,
                from: format!("{MEMORY_ENV} = {bytes}"),
            }));
        }
        let meminfo = mem_available().map(|bytes| Self {
            bytes,
            from: "MemAvailable".into(),
        });
        let cgroup = cgroup_left().map(|(bytes, file)| Self {
            bytes,
            from: format!("{} less memory.current", file.display()),
        });
        Ok(match (meminfo, cgroup) {
            (Some(m), Some(c)) => Some(if c.bytes < m.bytes { c } else { m }),
            (m, c) => m.or(c),
        })
    }

    /// [`DISK_ENV`] if set; otherwise the free space of the file system holding `dir` (or its
    /// nearest existing ancestor).
    pub fn disk(dir: &Path) -> Result<Option<Self>, ResourceError> {
        if let Some(bytes) = from_env(DISK_ENV)? {
            return Ok(Some(Self {
                bytes,
                from: format!("{DISK_ENV} = {bytes}"),
            }));
        }
        let Some(existing) = dir.ancestors().find(|d| d.exists()) else {
            return Ok(None);
        };
        let existing = if existing.as_os_str().is_empty() {
            Path::new(".")
        } else {
            existing
        };
        Ok(free_bytes(existing).map(|bytes| Self {
            bytes,
            from: format!("free on {}", existing.display()),
        }))
    }
}

/// Refuses `config` for `job` where its memory estimate exceeds what the process may use,
/// naming the keys behind the estimate; passes where the machine does not say.
pub fn check_memory(config: &Config, job: Job) -> Result<(), ResourceError> {
    check_needs(config, &Needs::of(config, job))
}

/// The worlds an evaluation of `episodes` builds: one per start cell (or the one fixed start)
/// where it is `exact` and the task's world is deterministic (no moving rain), whatever
/// `episodes`; else one per episode.
pub fn evaluation_worlds(config: &Config, task: &TaskConfig, episodes: usize, exact: bool) -> u64 {
    let deterministic = task.rain_moves_every.is_none() || task.rain.is_none();
    match exact && deterministic {
        true => config.world.exact_starts() as u64,
        false => episodes as u64,
    }
}

/// [`check_memory`] of `job` with `worlds` evaluated episodes that a command-line flag asks for
/// beside the config's own sizes, the refusal naming the flag (`flag`, such as `--episodes =
/// 1000000000`): each episode's world, its tables and its steps.
pub fn check_memory_with_episodes(
    config: &Config,
    job: Job,
    flag: String,
    worlds: u64,
) -> Result<(), ResourceError> {
    let mut needs = Needs::of(config, job);
    needs.sizes.push(Term {
        key: flag,
        what: "each episode's world, its tables and its steps",
        bytes: world_table_bytes(&config.world).saturating_add(episode_bytes(&config.world)),
        count: worlds,
    });
    check_needs(config, &needs)
}

/// `needs` against the memory the process may use; passes where the machine does not say.
fn check_needs(config: &Config, needs: &Needs) -> Result<(), ResourceError> {
    let Some(available) = Available::memory()? else {
        tracing::warn!("cannot read MemAvailable or the cgroup's memory.max; memory unchecked");
        return Ok(());
    };
    check_memory_against(config, needs, &available)
}

/// [`check_memory`] against a figure given.
pub fn check_memory_against(
    config: &Config,
    needs: &Needs,
    available: &Available,
) -> Result<(), ResourceError> {
    let memory = needs.memory();
    if memory <= available.bytes {
        return Ok(());
    }
    Err(ResourceError::Memory {
        origin: config.origin.clone(),
        message: memory_refusal(config, needs, memory, available),
    })
}

/// What a job that does not fit the memory available needs, by key, largest first.
fn memory_refusal(config: &Config, needs: &Needs, memory: u64, available: &Available) -> String {
    let mut terms: Vec<&Term> = needs.sizes.iter().collect();
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
    let processes = match needs.job {
        Job::Launch => format!(
            " ({} tasks x collect.actors_per_task = {} make {} processes)",
            config.tasks.len(),
            config.collect.actors_per_task,
            needs.processes
        ),
        _ => String::new(),
    };
    format!(
        "the config needs about {} of memory and {} is available ({}); expected sizes that fit; \
         by key, largest first (those of 1% or more): {}{processes}",
        gb(memory),
        gb(available.bytes),
        available.from,
        listed.join("; "),
    )
}

/// Refuses writing `bytes` (what `key` makes a run write) under `dir` where its disk has less
/// free; passes where the disk does not say.
pub fn check_disk(config: &Config, dir: &Path, key: &str, bytes: u64) -> Result<(), ResourceError> {
    let Some(available) = Available::disk(dir)? else {
        return Ok(());
    };
    if bytes <= available.bytes {
        return Ok(());
    }
    Err(ResourceError::Disk {
        origin: config.origin.clone(),
        message: format!(
            "{key} makes the run write up to {} under {} and {} is available ({}); expected a \
             size that fits",
            gb(bytes),
            dir.display(),
            gb(available.bytes),
            available.from
        ),
    })
}

/// The most a run's datasets take on disk: `collect.transitions` per dataset, `files` of them.
pub fn datasets_file_bytes(config: &Config, files: u64) -> u64 {
    (config.collect.transitions as u64)
        .saturating_mul(transition_file_bytes(config.world.devices))
        .saturating_mul(files)
}

fn gb(bytes: u64) -> String {
    format!("{:.1} GB", bytes as f64 / 1e9)
}

fn from_env(name: &'static str) -> Result<Option<u64>, ResourceError> {
    match std::env::var(name) {
        Ok(value) => value
            .trim()
            .parse()
            .map(Some)
            .map_err(|_| ResourceError::Env { name, value }),
        Err(std::env::VarError::NotPresent) => Ok(None),
        Err(std::env::VarError::NotUnicode(value)) => Err(ResourceError::Env {
            name,
            value: value.to_string_lossy().into_owned(),
        }),
    }
}

fn mem_available() -> Option<u64> {
    let text = std::fs::read_to_string("/proc/meminfo").ok()?;
    let line = text.lines().find(|l| l.starts_with("MemAvailable:"))?;
    let kib: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kib * 1024)
}

/// What the process's cgroup (v2) leaves of its `memory.max`, and that file; `None` where it
/// is `max` (no limit) or unreadable.
fn cgroup_left() -> Option<(u64, PathBuf)> {
    let membership = std::fs::read_to_string("/proc/self/cgroup").ok()?;
    let path = membership
        .lines()
        .find_map(|l| l.strip_prefix("0::"))
        .unwrap_or("/");
    let dir = Path::new("/sys/fs/cgroup").join(path.trim_start_matches('/'));
    let file = dir.join("memory.max");
    let max: u64 = std::fs::read_to_string(&file).ok()?.trim().parse().ok()?;
    let current: u64 = std::fs::read_to_string(dir.join("memory.current"))
        .ok()
        .and_then(|t| t.trim().parse().ok())
        .unwrap_or(0);
    Some((max.saturating_sub(current), file))
}

fn free_bytes(path: &Path) -> Option<u64> {
    use std::os::unix::ffi::OsStrExt;
    let path = std::ffi::CString::new(path.as_os_str().as_bytes()).ok()?;
    // SAFETY: statvfs writes the struct it is given; the path is a valid C string.
    let stat = unsafe {
        let mut stat = std::mem::zeroed::<libc::statvfs>();
        (libc::statvfs(path.as_ptr(), &mut stat) == 0).then_some(stat)?
    };
    Some((stat.f_bavail as u64).saturating_mul(stat.f_frsize as u64))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn on(bytes: u64) -> Available {
        Available {
            bytes,
            from: "a test".into(),
        }
    }

    fn refusal(config: &Config, job: Job, bytes: u64) -> String {
        check_memory_against(config, &Needs::of(config, job), &on(bytes))
            .expect_err("too much memory")
            .to_string()
    }

    #[test]
    fn a_replay_buffer_beyond_memory_is_refused_naming_the_key_the_value_and_the_estimate() {
        let mut config = Config::default();
        config.collect.dqn.replay_capacity = 1_000_000_000;
        let refused = refusal(&config, Job::Collect, 24 << 30);
        let each = 1e9 * std::mem::size_of::<Transition>() as f64 / 1e9;
        assert!(
            refused.contains("collect.dqn.replay_capacity = 1000000000")
                && refused.contains(&format!("{each:.1} GB"))
                && refused.contains("25.8 GB is available (a test)"),
            "{refused}"
        );
    }

    #[test]
    fn wide_networks_are_refused_in_the_jobs_that_train_them_only() {
        let mut config = Config::default();
        config.learner.hidden = vec![200_000, 200_000];
        let refused = refusal(&config, Job::Train, 24 << 30);
        assert!(
            refused.contains("learner.hidden = [200000, 200000]"),
            "{refused}"
        );
        let needs = Needs::of(&config, Job::Collect);
        check_memory_against(&config, &needs, &on(24 << 30)).expect("collect trains no learner");
        config.collect.dqn.hidden = vec![100_000, 100_000];
        let refused = refusal(&config, Job::Collect, 24 << 30);
        assert!(
            refused.contains("collect.dqn.hidden = [100000, 100000]"),
            "{refused}"
        );
    }

    #[test]
    fn the_default_config_fits_every_job_in_two_gigabytes() {
        let config = Config::default();
        for job in [
            Job::Collect,
            Job::Train,
            Job::MetaTrain,
            Job::Eval,
            Job::Store,
            Job::Python {
                worlds: 64,
                evaluation: true,
                planner: true,
            },
        ] {
            let needs = Needs::of(&config, job);
            check_memory_against(&config, &needs, &on(2 << 30)).expect("the default fits");
        }
    }

    #[test]
    fn a_dataset_beyond_the_disk_is_refused_naming_the_key_and_the_disk() {
        let config = Config::default();
        let bytes = datasets_file_bytes(&config, 1);
        let refused = check_disk(
            &config,
            Path::new("/nonexistent/dir"),
            "collect.transitions",
            bytes,
        );
        // Without DISK_ENV set this reads the root's free space, which holds 2000 transitions.
        refused.expect("the default fits");
    }
}
