//! `uavmeta env`: being written.
use anyhow::Result;
use clap::Subcommand;
#[derive(Subcommand)]
pub enum EnvCommand {}
pub fn run(c: EnvCommand) -> Result<()> { match c {} }
