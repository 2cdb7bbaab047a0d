//! The behaviour policies an actor can run: fixed heuristics, a Q-network's greedy policy, and the
//! online DQN agent whose replay buffer becomes the paper's datasets.

pub mod dqn_online;
pub mod dqn_population;
pub mod q_policy;

pub use uavmeta_world::heuristics;
