//! The Q-network and the offline algorithms: everything that learns from transitions, and nothing
//! about the world.
//!
//! - [`algorithm`]: [`algorithm::OfflineAlgorithm`], the loss an offline algorithm minimises,
//!   and [`algorithm::ALGORITHMS`], where each is registered; one file each:
//!   - [`cql`]: conservative Q-learning, paper eq. 8;
//!   - [`bc`]: behaviour cloning (d3rlpy's DiscreteBC), the offline baseline;
//!   - [`bcq`]: discrete batch-constrained Q-learning (d3rlpy's DiscreteBCQ): Q-learning over
//!     the actions an imitation head says the data supports;
//!   - [`dqn`]: DQN, paper eq. 7, and the one TD-target computation every learner uses
//!     ([`dqn::TdConfig::td_errors`]; double DQN and Huber as options, off by default).
//! - [`qnet`]: [`qnet::QNetwork`], the MLP of docs/MODEL.md section 5, built by
//!   [`qnet::QNetworkConfig::init`] with a seeded, global-state-free initialisation, and a
//!   functional forward pass on explicit (fast) weights for MAML.
//! - [`optim`]: [`optim::FusedAdam`], libtorch's one-pass Adam kernel, which tch does not wrap.
//! - [`transitions`]: [`transitions::Transitions`], `proto::dataset` transitions as normalised tensors.
//! - [`train`]: offline training with any registered algorithm, evaluated each epoch through the
//!   [`train::EvaluatePolicy`] hook; per-epoch table on stderr and `train.csv`.
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
//! One CQL gradient step by hand (offline training, [`train::train`], loops this):
//!
//! ```
//! use tch::nn::OptimizerConfig;
//! use uavmeta_learner::transitions::Transitions;
//! use uavmeta_learner::cql::{conservative_term, cql_loss};
//! use uavmeta_learner::qnet::{QNetwork, QNetworkConfig};
//! use uavmeta_proto::{config::WorldConfig, dataset::Transition};
//!
//! // K = 2 devices: observations [x, y, A_1, A_2], 2 + K = 4 inputs, 5K = 10 actions.
//! let world = WorldConfig { devices: 2, ..WorldConfig::default() };
//! let t = Transition {
//!     task: 0, actor: 0, episode: 0, step: 0, seq: 0,
//!     obs: vec![4, 5, 1, 1], action: 3, reward: -2.0, next_obs: vec![4, 6, 2, 1], truncated: false,
//! };
//! let batch = Transitions::new(&[t], &world, 0.01).unwrap();
//! let q = QNetworkConfig::for_world(&world, &[16, 16]).init(7);
//! let target = q.duplicate();
//! let mut adam = tch::nn::Adam::default().build(&q.vs, 1e-3).unwrap();
//!
//! let next_q_target = tch::no_grad(|| target.forward(&batch.next_obs)); // [1, 10]
//! let q_all = q.forward(&batch.obs); // Q_w(s, .) [1, 10]
//! let loss = cql_loss(&q_all, &next_q_target, &batch, 0.99, 1.0); // eq. 8
//! // The conservative term is never negative: logsumexp over actions bounds every Q(s, a).
//! assert!(conservative_term(&q_all, &batch).double_value(&[]) >= 0.0);
//! adam.backward_step(&loss);
//! // MAML's fast weights run through the same network function.
//! let same = QNetwork::forward_with(&q.parameters(), &batch.obs);
//! assert!(same.equal(&q.forward(&batch.obs)));
//! ```

pub mod algorithm;
pub mod bc;
pub mod bcq;
pub mod checkpoint;
pub mod cql;
pub mod dqn;
pub mod numerics;
pub mod optim;
pub mod progress;
pub mod qnet;
pub mod train;
pub mod transitions;
