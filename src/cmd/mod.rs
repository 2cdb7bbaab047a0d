//! One module per subcommand: each parses its flags and calls library code.

pub mod actor;
pub mod collect;
pub mod common;
pub mod dataset;
pub mod env;
pub mod eval;
pub mod launch;
pub mod meta;
pub mod reproduce;
pub mod train;
pub mod tunnel;
