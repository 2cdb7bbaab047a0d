//! Q-network, DQN and CQL: being written.
