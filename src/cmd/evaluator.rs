//! `uavmeta evaluator --run R`: scores every checkpoint the run announces (see
//! `uavmeta_runtime::evaluator`).

use anyhow::Result;
use clap::Args;

use super::launch::RunArgs;

#[derive(Args, Debug)]
pub struct EvaluatorArgs {
    #[command(flatten)]
    pub run: RunArgs,
}

pub fn run(args: EvaluatorArgs) -> Result<()> {
    let (run, config) = args.run.open()?;
    uavmeta_runtime::evaluator::run(&run, &config)?;
    Ok(())
}
