//! The Q-network and the offline algorithms: everything that learns from transitions, and nothing
//! about the world.
//!
//! - [`algorithm`]: [`algorithm::OfflineAlgorithm`], the loss an offline algorithm minimises,
//!   and [`algorithm::ALGORITHMS`], where each is registered; one file each:
//!   - [`cql`]: conservative Q-learning, paper eq. 8;
//!   - [`bc`]: behaviour cloning (d3rlpy's DiscreteBC), the offline baseline;
//!   - [`bcq`]: discrete batch-constrained Q-learning (d3rlpy's DiscreteBCQ): Q-learning over
//!     the actions an imitation head says the data supports;
//!   - [`dyna_cql`]: Dyna-CQL, the model-based learner: CQL on the shots plus rollouts in the
//!     world the shots identify ([`model_rows`]);
//!   - [`dqn`]: DQN, paper eq. 7, and the one TD-target computation every learner uses
//!     ([`dqn::TdConfig::td_errors`]; double DQN and Huber as options, off by default).
//! - [`qnet`]: [`qnet::QNetwork`], the MLP of docs/MODEL.md section 5, built by
//!   [`qnet::QNetworkConfig::init`] with a seeded, global-state-free initialisation, and a
//!   functional forward pass on explicit (fast) weights for MAML.
//! - [`optim`]: [`optim::FusedAdam`], libtorch's one-pass Adam kernel, which tch does not wrap.
//! - [`transitions`]: [`transitions::Transitions`], `proto::dataset` transitions as normalised tensors.
//! - [`train`]: offline training with any registered algorithm, evaluated each epoch through the
//!   [`train::EvaluatePolicy`] hook; per-epoch table on stderr and `train.csv`.
//! - [`model_rows`]: Dyna-CQL's model rows, rollouts of its policy in the world its shots
//!   identify, added to each epoch's shots.
//! - [`progress`]: the CSV log and the progress bar of a training loop (offline and meta), and
//!   [`progress::OnStep`], the hook a caller hears every training step through.
//! - [`numerics`]: the environment that pins libtorch's kernels (MKL's branch, ATen's vector
//!   width), so results are the same bits on another CPU.
//! - [`checkpoint`]: safetensors weights + JSON metadata + the run's config, written atomically
//!   and checked (sizes, length, CRC32) on load.
//!
//! It consumes transitions from `uavmeta-proto`'s dataset files and the `[learner]` config
//! section. Evaluating a policy needs the world (`uavmeta-world`); `uavmeta-actors`
//! implements the evaluation hook and the online DQN agent on top of these types.
//!
//! The losses, worked by hand: learner/tests/losses.rs; the network and its functional forward
//! pass for MAML's fast weights: learner/tests/network.rs.

pub mod algorithm;
pub mod bc;
pub mod bcq;
pub mod checkpoint;
pub mod cql;
pub mod dqn;
pub mod dyna_cql;
pub mod model_rows;
pub mod numerics;
pub mod optim;
pub mod progress;
pub mod qnet;
pub mod train;
pub mod transitions;
