//! What a run will ask of this machine, estimated from its config before anything starts, and
//! refused, naming the key and the estimate, when the machine cannot hold it: shared memory for
//! every actor's batches (against the free space of /dev/shm), memory for every process and for
//! every size a config sets (the one estimate and check every subcommand runs,
//! [`uavmeta_proto::resources`], for [`Job::Launch`]), and the disk of the run directory for its
//! datasets.

use uavmeta_proto::config::Config;
use uavmeta_proto::resources::{self, Job, Needs};

use super::LaunchError;
use crate::transport;

/// Shared memory of one actor's batches, times the actors of the run.
pub fn shm_needs(config: &Config) -> (u64, u64) {
    let actors = (config.tasks.len() * config.collect.actors_per_task) as u64;
    (transport::actor_shared_memory(&config.run), actors)
}

/// Refuses the run's actors' batches beyond `shm_bytes` of /dev/shm, naming the keys.
pub fn check_shm(config: &Config, shm_bytes: u64) -> Result<(), LaunchError> {
    let (per_actor, actors) = shm_needs(config);
    let shm = per_actor.saturating_mul(actors);
    if shm > shm_bytes {
        return Err(LaunchError::Resources { message: format!(
            "run.transitions_per_message = {} with run.subscriber_buffer = {} needs {} of shared memory per \
             actor, {} for {} actors; /dev/shm has {} free",
            config.run.transitions_per_message,
            config.run.subscriber_buffer,
            gb(per_actor),
            gb(shm),
            actors,
            gb(shm_bytes)
        )});
    }
    Ok(())
}
/// Checks the run against this machine: /dev/shm, the memory every process of the launch may
/// use ([`resources::check_memory`]) and the run directory's disk for its datasets.
pub fn check_here(config: &Config) -> Result<(), LaunchError> {
    match free_bytes("/dev/shm") {
        Some(shm_bytes) => check_shm(config, shm_bytes)?,
        None => tracing::warn!("cannot read /dev/shm's free space; shared memory unchecked"),
    }
    let refuse = |e: resources::ResourceError| LaunchError::Resources {
        message: e.to_string(),
    };
    resources::check_memory(config, Job::Launch).map_err(refuse)?;
    let datasets = resources::datasets_file_bytes(config, config.tasks.len() as u64);
    let key = format!(
        "collect.transitions = {} for {} tasks",
        config.collect.transitions,
        config.tasks.len()
    );
    resources::check_disk(config, &config.run.dir, &key, datasets).map_err(refuse)
}

/// The launch's memory estimate, as every subcommand's ([`Needs::of`] for [`Job::Launch`]).
pub fn memory_needs(config: &Config) -> Needs {
    Needs::of(config, Job::Launch)
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_huge_batch_is_refused_naming_the_key_and_both_figures() {
        let mut config = Config::default();
        config.run.transitions_per_message = 16_384;
        let refused = check_shm(&config, 2_000_000_000)
            .expect_err("too big")
            .to_string();
        assert!(
            refused.contains("run.transitions_per_message = 16384"),
            "{refused}"
        );
        assert!(refused.contains("/dev/shm has 2.0 GB free"), "{refused}");
        config.run.transitions_per_message = 64;
        check_shm(&config, 2_000_000_000).expect("the default fits");
    }

    #[test]
    fn a_large_world_times_many_processes_is_refused_naming_the_world() {
        let mut config = Config::default();
        config.world.grid_cells = 500;
        config.world.devices = 64;
        config.collect.actors_per_task = 7;
        let available = resources::Available {
            bytes: 24 << 30,
            from: "a test".into(),
        };
        let refused = resources::check_memory_against(&config, &memory_needs(&config), &available)
            .expect_err("too much memory")
            .to_string();
        assert!(refused.contains("world.grid_cells = 500"), "{refused}");
        assert!(refused.contains("make 68 processes"), "{refused}");
    }
}
