//! The `uavmeta` binary: parses arguments and calls library code, one subcommand per job.

use std::io::{IsTerminal, Write};
use std::process::ExitCode;

use clap::{Parser, Subcommand};
use indicatif::MultiProgress;
use uavmeta_proto::resources::Job;

mod cmd;

#[derive(Parser)]
#[command(
    name = "uavmeta",
    version,
    about = "Few-shot meta-offline RL (CQL inside MAML) for UAV trajectory and scheduling"
)]
struct Cli {
    /// libtorch intra-op threads. The Q-networks are small: one thread is as fast as two on an
    /// idle machine and immune to OpenMP spin-waiting on a busy one, where more threads made
    /// training 10-25x slower (docs/BENCHMARKS.md).
    #[arg(long, global = true, default_value_t = 1, value_name = "N")]
    torch_threads: i32,
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Inspect the UAV world: roll out a policy and print episode metrics.
    #[command(subcommand)]
    Env(cmd::env::EnvCommand),
    /// Collect one task's offline dataset with a behaviour policy.
    Collect(cmd::collect::CollectArgs),
    /// Export a dataset for Minari or d3rlpy, or inspect one.
    #[command(subcommand)]
    Dataset(cmd::dataset::DatasetCommand),
    /// Train a Q-network offline (CQL or DQN) on N shots of one task's dataset.
    Train(cmd::train::TrainArgs),
    /// Evaluate a checkpoint's greedy policy on a task, with 95% confidence intervals.
    Eval(cmd::eval::EvalArgs),
    /// Meta-train w0 with MAML over CQL or DQN (Algorithm 4) from one dataset per meta-train task.
    MetaTrain(cmd::meta::MetaTrainArgs),
    /// Fine-tune a meta-trained w0 on N shots of an unseen task, evaluating every epoch.
    MetaTest(cmd::meta::MetaTestArgs),
    /// Reproduce the paper's figures 4-9 over several seeds, each beside the claim it tests.
    Reproduce(cmd::reproduce::ReproduceArgs),
    /// Run everything (store, actors, meta-learner, evaluator) as one supervised run.
    Launch(cmd::launch::LaunchArgs),
    /// One actor of a run: roll out a behaviour policy and publish its transitions.
    Actor(cmd::actor::ActorArgs),
    /// The dataset store of a run: append every task's transitions to its dataset file.
    Store(cmd::launch::RunArgs),
    /// The meta-learner of a run: MAML over the run's datasets, then meta-test.
    MetaLearner(cmd::launch::RunArgs),
    /// The evaluator of a run: score every announced checkpoint in the true world.
    Evaluator(cmd::launch::RunArgs),
    /// Remote actor hosts: serve a run through iceoryx2's tunnel over Zenoh, or join one.
    #[command(subcommand)]
    Tunnel(cmd::tunnel::TunnelCommand),
}

impl Command {
    /// A command that does one job and exits, as against a process that serves a run until it
    /// is told to stop (`launch`, its children, the tunnel).
    fn ends_by_itself(&self) -> bool {
        !matches!(
            self,
            Command::Launch(_)
                | Command::Actor(_)
                | Command::Store(_)
                | Command::MetaLearner(_)
                | Command::Evaluator(_)
                | Command::Tunnel(_)
        )
    }
}

/// `uavmeta eval ... | head -1` ends quietly, as any Unix tool does, when the reader closes the
/// pipe: SIGPIPE's default action ends the process. Rust ignores SIGPIPE, which turns a closed
/// pipe into a panic in `println!`. Processes that serve a run keep ignoring it: a closed pipe
/// must not take a supervisor down and orphan its children.
fn end_quietly_on_a_closed_pipe() {
    // SAFETY: setting a signal's disposition to its default; no handler runs Rust code.
    unsafe {
        libc::signal(libc::SIGPIPE, libc::SIG_DFL);
    }
}

/// stderr for log lines, through the rows a command draws on the terminal (`uavmeta launch`'s
/// display): the rows are erased, the line written, the rows drawn again below it. A line written
/// straight between the rows would shift them, leaving rows drawn twice.
struct AboveRows(MultiProgress);

impl Write for AboveRows {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        self.0.suspend(|| std::io::stderr().write(buf))
    }

    fn flush(&mut self) -> std::io::Result<()> {
        std::io::stderr().flush()
    }
}

fn main() -> ExitCode {
    // Before any thread or libtorch call: the same bits on another CPU (learner::numerics).
    if let Err(error) = uavmeta_learner::numerics::pin() {
        eprintln!("uavmeta: {error}");
        return ExitCode::FAILURE;
    }
    let terminal = MultiProgress::new();
    let rows = terminal.clone();
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info")),
        )
        .with_writer(move || AboveRows(rows.clone()))
        .with_ansi(std::io::stderr().is_terminal())
        .init();
    let cli = Cli::parse();
    if cli.command.ends_by_itself() {
        end_quietly_on_a_closed_pipe();
    }
    tch::set_num_threads(cli.torch_threads.max(1));
    let result = match cli.command {
        Command::Env(c) => cmd::env::run(c),
        Command::Collect(c) => cmd::collect::run(c),
        Command::Dataset(c) => cmd::dataset::run(c),
        Command::Train(c) => cmd::train::run(c),
        Command::Eval(c) => cmd::eval::run(c),
        Command::MetaTrain(c) => cmd::meta::run_train(c),
        Command::MetaTest(c) => cmd::meta::run_test(c),
        Command::Reproduce(c) => cmd::reproduce::run(c),
        Command::Launch(c) => cmd::launch::run(c, terminal),
        Command::Actor(c) => cmd::actor::run(c),
        Command::Store(c) => c.serve(Job::Store, uavmeta_runtime::store::run),
        Command::MetaLearner(c) => c.serve(Job::MetaTrain, uavmeta_runtime::meta_learner::run),
        Command::Evaluator(c) => c.serve(Job::Eval, uavmeta_runtime::evaluator::run),
        Command::Tunnel(c) => cmd::tunnel::run(c),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(error) => {
            eprintln!("uavmeta: {error:#}");
            ExitCode::FAILURE
        }
    }
}
