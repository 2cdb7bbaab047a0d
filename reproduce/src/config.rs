//! `[reproduce]`: the sizes of the paper's section V experiments (docs/MODEL.md section 6). This
//! crate alone reads the section, so it declares it: the experiment config keeps the table as
//! written (`uavmeta_proto::config::OwnedSection`) and [`ReproduceConfig::of`] reads and checks it
//! when a reproduction starts, so that other commands accept a config whose tasks do not fit it.

use garde::Validate;
use serde::{Deserialize, Serialize};
use smart_default::SmartDefault;

use uavmeta_proto::config::rules::{at_least, increasing, non_empty, Broken};
use uavmeta_proto::config::{Config, ConfigError, OwnedSection, Section, TaskConfig, TaskRole};

/// `uavmeta reproduce`: the sizes of the paper's section V experiments (docs/MODEL.md section 6).
/// Keys that name tasks or count them, and the seeds, are checked against the other sections by
/// [`ReproduceConfig::of`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, SmartDefault, Validate)]
#[serde(deny_unknown_fields, default)]
#[garde(allow_unvalidated)]
pub struct ReproduceConfig {
    /// Seeds 0..seeds-1 behind every curve; seed s collects its own datasets with
    /// `collect.seed + s`, so the spread covers the data as well as the learning.
    #[default(5)]
    pub seeds: usize,
    /// The main experiments meta-train on the first this many meta-train tasks, in config order.
    #[default(8)]
    #[garde(custom(at_least(1)))]
    pub meta_tasks: usize,
    /// Figure 7: meta-train on the first n meta-train tasks for each n.
    #[default(vec![2, 4, 6, 8, 10])]
    #[garde(custom(increasing("a non-empty, strictly increasing list of task counts >= 1")))]
    pub task_counts: Vec<usize>,
    /// Figure 6: the shot counts CQL and CQL-MAML are fine-tuned on.
    #[default(vec![100, 300, 500])]
    #[garde(custom(increasing("a non-empty, strictly increasing list of shot counts >= 1")))]
    pub shots: Vec<usize>,
    /// Shots of every other experiment (the paper's 500).
    #[default(500)]
    #[garde(custom(at_least(1)))]
    pub main_shots: usize,
    /// The unseen task of figures 5-8 (role `meta-test`).
    #[default("lambda-300")]
    #[garde(custom(non_empty("a task name")))]
    pub unseen_task: String,
    /// Figures 5 and 6: fine-tuning epochs.
    #[default(100)]
    #[garde(custom(at_least(1)))]
    pub convergence_epochs: usize,
    /// Figure 7: fine-tuning epochs after which the task counts are compared.
    #[default(40)]
    #[garde(custom(at_least(1)))]
    pub tasks_epochs: usize,
    /// Figure 8: the epoch whose AoI and power are compared.
    #[default(50)]
    #[garde(custom(at_least(1)))]
    pub aoi_power_epoch: usize,
    /// Figure 9: fine-tuning epochs on each rain task (meta-test tasks with a rain zone).
    #[default(200)]
    #[garde(custom(at_least(1)))]
    pub resilience_epochs: usize,
    /// Figure 9: Monte-Carlo episodes of each evaluation on a rain task.
    #[default(40)]
    #[garde(custom(at_least(1)))]
    pub resilience_eval_episodes: usize,
    /// Figure 4: meta-epochs between evaluations of the adapted policies; 0 evaluates only after
    /// the last. The inits no figure draws a curve of are evaluated only after the last.
    #[default(10)]
    pub meta_eval_every: usize,
    /// `--engine slurm`'s submission settings (`crate::slurm`); they change where jobs run, not
    /// what they make.
    #[garde(dive)]
    pub slurm: crate::slurm::SlurmConfig,
}

impl Section for ReproduceConfig {
    const KEY: &'static str = "reproduce";
}

impl ReproduceConfig {
    /// `config`'s `[reproduce]`, each key it leaves out at its default, checked alone and against
    /// `[[tasks]]` and `[collect]`: an error names the config's file, the key, the value and what
    /// was expected.
    pub fn of(config: &Config) -> Result<Self, ConfigError> {
        let r: Self = config.reproduce.read(&config.origin)?;
        r.check_seeds(config.collect.seed)
            .and_then(|()| r.check_against(&config.tasks, config.collect.transitions))
            .map_err(|broken| broken.at(&config.origin))?;
        Ok(r)
    }

    /// Writes these settings, every key, into `config`'s `[reproduce]`.
    pub fn write_into(&self, config: &mut Config) {
        config.reproduce = OwnedSection::of(self);
    }

    /// At least one seed, and seed s's `collect_seed + s` (its collection's seed) fits TOML's i64.
    fn check_seeds(&self, collect_seed: u64) -> Result<(), Broken> {
        let last = (self.seeds as u64)
            .checked_sub(1)
            .map(|s| s.checked_add(collect_seed));
        match last {
            Some(Some(last)) if last <= i64::MAX as u64 => Ok(()),
            _ => Err(Broken::new(
                "reproduce.seeds",
                &self.seeds,
                format!(
                    "at least 1, with collect.seed + seeds - 1 at most {}",
                    i64::MAX
                ),
            )),
        }
    }

    /// The keys that name tasks or count them fit `tasks`, and the shots fit datasets of
    /// `transitions` each.
    fn check_against(&self, tasks: &[TaskConfig], transitions: usize) -> Result<(), Broken> {
        let meta_train = tasks
            .iter()
            .filter(|t| t.role == TaskRole::MetaTrain)
            .count();
        let of_meta_train = format!("{meta_train} tasks with role = \"meta-train\"");
        if self.meta_tasks > meta_train {
            let expected = format!("at most the {of_meta_train}");
            return Err(Broken::new(
                "reproduce.meta_tasks",
                &self.meta_tasks,
                expected,
            ));
        }
        if self.task_counts.iter().any(|&n| n > meta_train) {
            let expected = format!("counts of at most the {of_meta_train}");
            return Err(Broken::new(
                "reproduce.task_counts",
                &self.task_counts,
                expected,
            ));
        }
        let unseen = |t: &TaskConfig| t.name == self.unseen_task && t.role == TaskRole::MetaTest;
        if !tasks.iter().any(unseen) {
            let expected = "the name of a task with role = \"meta-test\"";
            return Err(Broken::new(
                "reproduce.unseen_task",
                &self.unseen_task,
                expected,
            ));
        }
        let most = self.shots.iter().copied().chain([self.main_shots]).max();
        match most.is_some_and(|most| most > transitions) {
            false => Ok(()),
            true => Err(Broken::new(
                "reproduce.shots / reproduce.main_shots",
                &(&self.shots, self.main_shots),
                format!(
                    "at most collect.transitions = {transitions}, the size of each task's dataset"
                ),
            )),
        }
    }
}
