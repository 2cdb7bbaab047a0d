//! Where a run keeps its files: the run directory's layout ([`RunDir`]), its config, the atomic
//! writes every process makes into it, and the identity of a remote actor host's directory, which
//! stands for the learner host's run.
//!
//! [`RunDir`] holds the config every process of the run reads, the datasets, checkpoints, metrics
//! port files and final metrics snapshots, logs, heartbeats and evaluation rows, and the
//! Prometheus and Grafana files of the run.

use std::path::{Path, PathBuf};

use uavmeta_proto::config::{Config, TaskConfig};
use uavmeta_proto::method::Method;

pub use uavmeta_proto::fs::{write_atomic, FileError};

/// A remote host that has not announced itself for this long is gone: out of the scrape targets.
pub const REMOTE_HOST_SILENCE: std::time::Duration = std::time::Duration::from_secs(10);

/// A run's directory and the layout of everything in it.
#[derive(Debug, Clone)]
pub struct RunDir {
    root: PathBuf,
    id: String,
    hash: u64,
    /// On a remote actor host, the host's name (its certificate's): its actors publish under it.
    host: Option<String>,
}

impl RunDir {
    /// Opens `path`, creating it and its subdirectories when missing. The run id is the
    /// directory's name plus a hash of its absolute path: readable in service names, and
    /// distinct for two runs whose directories share a name.
    pub fn create(path: &Path) -> Result<Self, FileError> {
        std::fs::create_dir_all(path).map_err(FileError::at(path, "create the run directory"))?;
        let run = Self::open(path)?;
        for sub in ["datasets", "checkpoints", "ports", "metrics", "logs"] {
            let dir = run.root.join(sub);
            std::fs::create_dir_all(&dir).map_err(FileError::at(&dir, "create"))?;
        }
        Ok(run)
    }

    /// The existing run directory `path`, with the id [`RunDir::create`] gives it; nothing is
    /// created.
    pub fn open(path: &Path) -> Result<Self, FileError> {
        let root = path
            .canonicalize()
            .map_err(FileError::at(path, "resolve the run directory"))?;
        let hash = fnv1a(root.to_string_lossy().as_bytes());
        let name: String = root
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_else(|| "root".into())
            .chars()
            .map(|c| {
                if c.is_ascii_alphanumeric() || c == '-' || c == '_' {
                    c
                } else {
                    '_'
                }
            })
            .take(64)
            .collect();
        let local = Self {
            id: format!("{name}-{:08x}", hash as u32),
            root,
            hash,
            host: None,
        };
        local
            .remote_identity()
            .map(|remote| remote.unwrap_or(local))
    }

    /// Makes `path` remote host `host`'s directory of run `id` (hash `hash`) of another host
    /// (`uavmeta tunnel join`): the processes started in it join that run as `host`'s, since id,
    /// hash (which come from the learner host's path) and host are read from [`REMOTE_RUN_FILE`].
    pub fn create_remote(path: &Path, id: &str, hash: u64, host: &str) -> Result<Self, FileError> {
        let local = Self::create(path)?;
        let file = local.root.join(REMOTE_RUN_FILE);
        write_atomic(&file, format!("{id}\n{hash:016x}\n{host}\n").as_bytes())?;
        Self::create(path)
    }

    /// The id and hash of the remote run this directory stands for, if it does.
    fn remote_identity(&self) -> Result<Option<Self>, FileError> {
        let file = self.root.join(REMOTE_RUN_FILE);
        let text = match std::fs::read_to_string(&file) {
            Ok(text) => text,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
            Err(e) => return Err(FileError::at(&file, "read")(e)),
        };
        let mut lines = text.lines();
        let parsed = (lines.next())
            .zip(lines.next().and_then(|h| u64::from_str_radix(h, 16).ok()))
            .zip(lines.next().filter(|h| !h.is_empty()));
        let parse = "parse (expected a run id, a hexadecimal hash and a host name)";
        let Some(((id, hash), host)) = parsed else {
            return Err(FileError::at(&file, parse)(
                std::io::ErrorKind::InvalidData.into(),
            ));
        };
        Ok(Some(Self {
            root: self.root.clone(),
            id: id.to_string(),
            hash,
            host: Some(host.to_string()),
        }))
    }

    /// Where the learner host's tunnel keeps what remote hosts announced: one file per host.
    pub fn remote_hosts_dir(&self) -> PathBuf {
        self.root.join("remote-hosts")
    }

    /// The remote actor hosts that announced themselves through the tunnel in the last
    /// [`REMOTE_HOST_SILENCE`], by name.
    pub fn remote_hosts(&self) -> Vec<RemoteHost> {
        let entries = std::fs::read_dir(self.remote_hosts_dir());
        let mut hosts: Vec<RemoteHost> = entries
            .into_iter()
            .flatten()
            .flatten()
            .filter(|entry| {
                (entry.metadata().and_then(|m| m.modified()).ok())
                    .and_then(|at| at.elapsed().ok())
                    .is_some_and(|age| age < REMOTE_HOST_SILENCE)
            })
            .filter_map(|entry| serde_json::from_slice(&std::fs::read(entry.path()).ok()?).ok())
            .collect();
        hosts.sort_by(|a, b| a.host.cmp(&b.host));
        hosts
    }

    pub fn root(&self) -> &Path {
        &self.root
    }

    /// The run's name in service names: `<dir name>-<hash>`.
    pub fn id(&self) -> &str {
        &self.id
    }

    /// On a remote actor host, the host's name; `None` on the learner's host.
    pub fn host(&self) -> Option<&str> {
        self.host.as_deref()
    }

    /// The run's service names as this host's actors use them.
    pub fn service_names(&self) -> uavmeta_proto::payload::ServiceNames {
        let names = uavmeta_proto::payload::ServiceNames::new(&self.id);
        match &self.host {
            Some(host) => names.for_host(host),
            None => names,
        }
    }

    /// A 64-bit fingerprint of the run's absolute path, carried by every batch.
    pub fn hash(&self) -> u64 {
        self.hash
    }

    /// The config every process of the run uses, written by the first process to start.
    pub fn config_file(&self) -> PathBuf {
        self.root.join("config.toml")
    }

    /// Task `task`'s dataset file, appended by the store.
    pub fn dataset(&self, task: &TaskConfig) -> PathBuf {
        self.root.join("datasets").join(format!(
            "{}.{}",
            task.name,
            uavmeta_proto::dataset::FILE_EXTENSION
        ))
    }

    /// The checkpoint (in `uavmeta_learner::checkpoint`'s naming) of `method` on `task` after
    /// `epoch` epochs; [`Method::MetaInit`] checkpoints belong to no task and ignore it.
    pub fn checkpoint(&self, method: Method, task: &TaskConfig, epoch: u32) -> PathBuf {
        let dir = self.root.join("checkpoints").join(method.name());
        let dir = if method == Method::MetaInit {
            dir
        } else {
            dir.join(&task.name)
        };
        dir.join(format!("epoch-{epoch:05}"))
    }

    /// Where process `process` writes the port of its /metrics endpoint.
    pub fn port_file(&self, process: &str) -> PathBuf {
        self.ports_dir().join(format!("{process}.port"))
    }

    /// Every process's port file ([`RunDir::port_file`]).
    pub fn ports_dir(&self) -> PathBuf {
        self.root.join("ports")
    }

    /// Where process `process` writes its last metrics when it exits.
    pub fn metrics_snapshot(&self, process: &str) -> PathBuf {
        self.root.join("metrics").join(format!("{process}.prom"))
    }

    /// The log file of a child process started by the launcher.
    pub fn log_file(&self, process: &str) -> PathBuf {
        self.root.join("logs").join(format!("{process}.log"))
    }

    /// The file whose modification time a launched process moves while it makes progress
    /// ([`heartbeat`](crate::liveness::heartbeat)).
    pub fn heartbeat_file(&self, process: &str) -> PathBuf {
        self.root.join("heartbeats").join(process)
    }

    /// The evaluator's rows, one per evaluated checkpoint.
    pub fn evaluations_csv(&self) -> PathBuf {
        self.root.join("evaluations.csv")
    }

    /// A Prometheus config that scrapes this run.
    pub fn prometheus_yml(&self) -> PathBuf {
        self.root.join("prometheus.yml")
    }

    /// The scrape targets (Prometheus file service discovery), rewritten as processes start.
    pub fn prometheus_targets(&self) -> PathBuf {
        self.root.join("prometheus-targets.json")
    }

    /// The Grafana dashboard of the run's metrics (a copy of `docs/grafana/uavmeta.json`), to
    /// import beside a Prometheus that reads [`RunDir::prometheus_yml`].
    pub fn grafana_dashboard(&self) -> PathBuf {
        self.root.join("grafana-dashboard.json")
    }

    /// Reads the run's config, or, on the run's first start, writes `fallback` as the run's config
    /// (atomically, so two processes starting together agree) and returns it.
    pub fn load_or_init_config(
        &self,
        fallback: impl FnOnce() -> Result<Config, uavmeta_proto::config::ConfigError>,
    ) -> Result<Config, RunConfigError> {
        let path = self.config_file();
        if path.exists() {
            return Ok(Config::load(&path, &[])?);
        }
        let config = fallback()?;
        write_atomic(&path, config.to_toml_string().as_bytes())?;
        Ok(Config::load(&path, &[])?)
    }
}

/// Reading or writing a run's config.
#[derive(Debug, thiserror::Error)]
pub enum RunConfigError {
    #[error(transparent)]
    Config(#[from] uavmeta_proto::config::ConfigError),
    #[error(transparent)]
    File(#[from] FileError),
}

/// FNV-1a of `bytes`: run ids and actor ids.
pub(crate) fn fnv1a(bytes: &[u8]) -> u64 {
    let mut hasher = fnv::FnvHasher::default();
    std::hash::Hasher::write(&mut hasher, bytes);
    std::hash::Hasher::finish(&hasher)
}

/// What a remote actor host announces to the learner's host (as JSON), which keeps the latest in
/// [`RunDir::remote_hosts_dir`] for the launcher's Prometheus targets and progress.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct RemoteHost {
    /// The host's name: the `host` label of its processes' metrics.
    pub host: String,
    pub processes: Vec<RemoteProcess>,
}

/// One process of a remote actor host.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct RemoteProcess {
    pub name: String,
    /// Where its /metrics answers, `address:port`.
    pub metrics: String,
}

/// The file in a remote actor host's run directory that names the learner host's run.
pub const REMOTE_RUN_FILE: &str = "remote-run";

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    /// A run directory in a fresh temporary directory (kept while the `TempDir` lives).
    pub(crate) fn test_run(name: &str) -> (tempfile::TempDir, RunDir) {
        let dir = tempfile::Builder::new()
            .prefix(name)
            .tempdir()
            .expect("temp dir");
        let run = RunDir::create(dir.path()).expect("run dir");
        (dir, run)
    }

    #[test]
    fn two_runs_have_their_own_ids_and_hashes() {
        let (_a, run_a) = test_run("run-a");
        let (_b, run_b) = test_run("run-b");
        assert_ne!(run_a.id(), run_b.id());
        assert_ne!(run_a.hash(), run_b.hash());
    }
}
