//! `uavmeta meta-learner --run R`: MAML over the run's datasets, then meta-test (see
//! `uavmeta_runtime::meta_learner`).

use anyhow::Result;
use clap::Args;

use super::launch::RunArgs;

#[derive(Args, Debug)]
pub struct MetaLearnerArgs {
    #[command(flatten)]
    pub run: RunArgs,
}

pub fn run(args: MetaLearnerArgs) -> Result<()> {
    let (run, config) = args.run.open()?;
    uavmeta_runtime::meta_learner::run(&run, &config)?;
    Ok(())
}
