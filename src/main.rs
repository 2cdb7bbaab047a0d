//! The `uavmeta` binary: parses arguments and calls library code, one subcommand per job.

use std::process::ExitCode;

use clap::{Parser, Subcommand};

mod cmd;

#[derive(Parser)]
#[command(name = "uavmeta", version, about = "Few-shot meta-offline RL (CQL inside MAML) for UAV trajectory and scheduling")]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Inspect the UAV world: roll out a policy and print episode metrics.
    #[command(subcommand)]
    Env(cmd::env::EnvCommand),
}

fn main() -> ExitCode {
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info")),
        )
        .with_writer(std::io::stderr)
        .init();
    let cli = Cli::parse();
    let result = match cli.command {
        Command::Env(c) => cmd::env::run(c),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(error) => {
            eprintln!("uavmeta: {error:#}");
            ExitCode::FAILURE
        }
    }
}
