//! One module per subcommand: each parses its flags and calls library code.

pub mod common;
pub mod env;
