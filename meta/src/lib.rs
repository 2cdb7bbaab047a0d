//! MAML over CQL or DQN inner loops: the paper's contribution, as a library. The experiments
//! that measure it are `uavmeta-reproduce`; the meta-learner process that runs it in a run and the
//! launcher are `uavmeta-runtime`'s.
//!
//! - [`maml`]: Algorithm 4 (eqs. 14-16) on [`uavmeta_learner::qnet::QNetwork`] fast weights, with
//!   the CQL loss (CQL-MAML) or the DQN loss (DQN-MAML), second or first order; its module doc
//!   says how the target network is handled and why.
//! - [`meta_train`]: meta-training from one dataset file per meta-train task
//!   (`<task-name>.uavds`), with a per-meta-epoch CSV, adapted-policy returns and `w0` checkpoints.
//! - [`pretrain`]: CQL-pretrain, one CQL network on the union of the meta-train tasks' shots,
//!   the multi-task baseline that shows what MAML adds.
//! - [`context`]: the task-inferring learner (FOCAL-style): a task encoder over a set of
//!   transitions and a task-conditioned Q-network, trained offline on the meta-train tasks; at
//!   meta-test it reads the unseen task's shots and acts with no gradient step.
//! - [`fine_tune`]: meta-test, fine-tuning a `w0` checkpoint on N shots of an unseen task, through
//!   the learner's offline training so every method shares its settings and CSV columns.
//!
//! It consumes datasets (`uavmeta_proto::dataset`), the Q-network, losses, training loop and
//! checkpoints of `uavmeta-learner`, the world of `uavmeta-world` and the greedy-policy evaluator
//! of `uavmeta-actors`; its results go to CSV files and checkpoints in an output directory. A
//! caller hears every training step through [`uavmeta_learner::progress::OnStep`].
//!
//! ```
//! use tch::Tensor;
//! use uavmeta_learner::transitions::Transitions;
//! use uavmeta_learner::qnet::QNetworkConfig;
//! use uavmeta_meta::maml::{Maml, MamlConfig, MetaTask};
//! use uavmeta_proto::config::Config;
//!
//! // Two transitions of a world with 1 device: 3 inputs, 5 actions.
//! let rows = |scale: f64| Transitions {
//!     obs: Tensor::from_slice(&[0.1f32, 0.2, 0.3, 0.4, 0.5, 0.6]).view([2, 3]) * scale,
//!     actions: Tensor::from_slice(&[0i64, 4]),
//!     rewards: Tensor::from_slice(&[-0.5f32, -0.2]),
//!     next_obs: Tensor::from_slice(&[0.2f32, 0.2, 0.1, 0.5, 0.4, 0.6]).view([2, 3]),
//! };
//! let tasks = vec![MetaTask { name: "a".into(), support: rows(1.0), query: rows(0.5) }];
//! // CQL-MAML with the defaults: one second-order inner step, eta_inner = 1e-2.
//! let settings = MamlConfig::from_config(&Config::default());
//! let mut maml = Maml::new(QNetworkConfig::new(3, 5, &[8]).init(1), settings, 0).unwrap();
//! let epoch = maml.meta_epoch(&tasks).unwrap();
//! assert_eq!(epoch.task_losses.len(), 1);
//! assert!(epoch.meta_loss.is_finite());
//! // The adapted network of a task: what its greedy policy is evaluated with.
//! let adapted = maml.adapted(&tasks[0].support);
//! assert_eq!(adapted.forward(&tasks[0].query.obs).size(), [2, 5]);
//! ```

pub mod context;
pub mod fine_tune;
pub mod maml;
pub mod meta_train;
pub mod pretrain;

use std::path::{Path, PathBuf};

use uavmeta_learner::checkpoint::CheckpointError;
use uavmeta_learner::train::TrainError;
use uavmeta_learner::transitions::{ShotsError, TransitionsError};
use uavmeta_proto::config::ConfigError;
use uavmeta_proto::dataset::DatasetError;
use uavmeta_proto::fs::FileError;

/// Everything meta-training and meta-testing can fail on.
#[derive(Debug, thiserror::Error)]
pub enum MetaError {
    #[error("meta-training needs at least one task")]
    NoTasks,
    #[error("{origin}: no task has role = \"meta-train\"; meta-training needs at least one")]
    NoMetaTrainTasks { origin: String },
    // The source is not in the message: `{:#}` prints the cause chain after it.
    #[error("{}", path.display())]
    Transitions {
        path: PathBuf,
        source: TransitionsError,
    },
    #[error("{}: trained by `{algorithm}`, expected a meta-trained, pretrained or context init (`cql-maml`, `dqn-maml`, `cql-pretrain` or `cql-context`)", path.display())]
    NotMetaTrained { path: PathBuf, algorithm: String },
    #[error(transparent)]
    File(#[from] FileError),
    #[error(transparent)]
    Config(#[from] ConfigError),
    #[error(transparent)]
    Dataset(#[from] DatasetError),
    #[error(transparent)]
    Checkpoint(#[from] CheckpointError),
    #[error(transparent)]
    Train(#[from] TrainError),
    #[error(transparent)]
    Torch(#[from] tch::TchError),
}

impl From<ShotsError> for MetaError {
    fn from(error: ShotsError) -> Self {
        match error {
            ShotsError::Dataset(e) => MetaError::Dataset(e),
            ShotsError::Transitions { path, source } => MetaError::Transitions { path, source },
        }
    }
}

/// Creates `dir` and its parents, naming it on failure.
pub fn create_dir(dir: &Path) -> Result<(), MetaError> {
    std::fs::create_dir_all(dir)
        .map_err(FileError::at(dir, "create"))
        .map_err(MetaError::from)
}

/// Writes `text` to `path`, naming it on failure.
pub fn write_file(path: &Path, text: &str) -> Result<(), MetaError> {
    std::fs::write(path, text)
        .map_err(FileError::at(path, "write"))
        .map_err(MetaError::from)
}
