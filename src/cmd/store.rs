//! `uavmeta store --run R`: the dataset store of a run (see `uavmeta_runtime::store`).

use anyhow::Result;
use clap::Args;

use super::launch::RunArgs;

#[derive(Args, Debug)]
pub struct StoreArgs {
    #[command(flatten)]
    pub run: RunArgs,
}

pub fn run(args: StoreArgs) -> Result<()> {
    let (run, config) = args.run.open()?;
    uavmeta_runtime::store::run(&run, &config)?;
    Ok(())
}
