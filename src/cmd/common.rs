//! Flags every command shares: the config file, `--set` overrides, and one-off tasks.

use std::path::PathBuf;

use anyhow::Result;
use clap::Args;
use uavmeta_proto::config::{Config, RainZone, TaskConfig};

/// `--config FILE` and any number of `--set KEY=VALUE`.
#[derive(Args, Debug, Clone)]
pub struct ConfigArgs {
    /// Experiment config (TOML, docs/MODEL.md section 7).
    #[arg(long, default_value = "configs/default.toml")]
    pub config: PathBuf,
    /// Override one key, dotted as in the file: `--set world.devices=20`, `--set
    /// tasks.0.lambda=50`.
    #[arg(long = "set", value_name = "KEY=VALUE")]
    pub overrides: Vec<String>,
}

impl ConfigArgs {
    /// The config of a command that flies one UAV: every command but `env rollout`.
    pub fn load(&self) -> Result<Config> {
        let config = self.load_team()?;
        config.require_one_uav("this command")?;
        Ok(config)
    }

    /// The config, a team's too.
    pub fn load_team(&self) -> Result<Config> {
        Ok(Config::load(&self.config, &self.overrides)?)
    }
}

/// The shots an offline run trains on: `--dataset FILE --shots N [--epochs E]`.
#[derive(Args, Debug, Clone)]
pub struct ShotsArgs {
    /// The task's dataset file.
    #[arg(long)]
    pub dataset: PathBuf,
    /// N: transitions drawn from the dataset to train (or fine-tune) on.
    #[arg(long, value_parser = clap::builder::RangedU64ValueParser::<usize>::new().range(1..))]
    pub shots: usize,
    /// Training epochs [default: learner.epochs].
    #[arg(long)]
    pub epochs: Option<usize>,
}

/// `--task NAME`, or a one-off task from `--lambda X [--rain x0,y0,x1,y1 [--rain-moves-every N]]`.
#[derive(Args, Debug, Clone)]
pub struct TaskArgs {
    /// A task named in the config.
    #[arg(long, conflicts_with = "lambda")]
    pub task: Option<String>,
    /// The lambda of a one-off task.
    #[arg(long)]
    pub lambda: Option<f64>,
    /// The rain zone of a one-off task, cells x0,y0,x1,y1 inclusive.
    #[arg(long, requires = "lambda")]
    pub rain: Option<RainZone>,
    /// Relocate the one-off task's rain zone uniformly at random every N steps.
    #[arg(long, requires = "rain", value_name = "N")]
    pub rain_moves_every: Option<u32>,
}

impl TaskArgs {
    /// The task these flags name, validated against the config's world like a task of the file.
    pub fn resolve(&self, config: &mut Config) -> Result<TaskConfig> {
        match (&self.task, self.lambda) {
            (Some(name), _) => Ok(config.task(name)?.clone()),
            (None, Some(lambda)) => {
                let rain = self.rain;
                let task = match (rain, self.rain_moves_every) {
                    (Some(zone), Some(every)) => TaskConfig::one_off_moving(lambda, zone, every),
                    _ => TaskConfig::one_off(lambda, rain),
                };
                if config.task(&task.name).is_err() {
                    config.tasks.push(task.clone());
                    config.validate()?;
                }
                Ok(task)
            }
            (None, None) => anyhow::bail!(
                "name a task with --task NAME, or define one with --lambda X [--rain x0,y0,x1,y1]"
            ),
        }
    }
}
