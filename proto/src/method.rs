//! Which algorithm trained a network and from where it started: one vocabulary for configs,
//! checkpoints, the evaluator's metrics, `launch`'s table, `reproduce`'s figures and the CLI.
//!
//! An [`Algo`] is an offline learning algorithm, registered by name in [`ALGORITHMS`] (its loss
//! is `uavmeta_learner::algorithm`'s of the same name). A [`Method`] is what a table row shows:
//! an algorithm fine-tuned on an unseen task's shots from a [`Start`] (`cql` from a random init,
//! `cql-maml` from the meta-learned w0, `cql-pretrain` from multi-task pretraining, `cql-context`
//! from the context learner's zero-shot policy), or one of the three rows that are not
//! fine-tuned (w0 alone, the context learner's zero-shot policy, the online agent).

use std::fmt;

use serde::{Deserialize, Deserializer, Serialize, Serializer};

/// One registered offline algorithm.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct AlgoInfo {
    /// In configs, `--algo`, checkpoints, file names and metric labels.
    pub name: &'static str,
    /// In figures and tables, as papers write it.
    pub label: &'static str,
    /// Whether a launch and the reproduction fine-tune it beside `meta.inner_loss` by default
    /// (`learner.baselines`).
    pub baseline: bool,
    /// Whether it learns from a model of the world too (its loss's `model_rows`): its rows stand
    /// in the tables' model-based section ([`MODEL_BASED`]), apart from the learners that read
    /// the shots alone.
    pub model_based: bool,
}

/// What the model-based section of every table is told beyond the shots.
pub const MODEL_BASED: &str = "model-based: told the moves, the AoI update, the reward's form and \
     the channel law; each device's power cost and any rain learnt from the shots";

/// The model-based section's reference row: the planner run in the world a seed's shots identify
/// (`uavmeta_world::heuristics::model_planner_metrics`), what planning in the fitted world
/// reaches.
pub const MODEL_PLANNER: &str = "model-planner";

/// What a table says of a task whose shots fit no world.
pub const NO_FITTED_WORLD: &str = "the shots fit no world (they show rain, or steps of another \
     world): the model-based rows trained on the shots alone, as their model-free algorithm does, \
     and there is no model-planner row (docs/MODEL.md section 5)";

/// Every offline algorithm, in wire order: one line each. Adding one here and its loss to
/// `uavmeta_learner::algorithm::ALGORITHMS` (same name, same order) is the whole registration.
#[rustfmt::skip]
pub const ALGORITHMS: &[AlgoInfo] = &[
    AlgoInfo { name: "cql", label: "CQL", baseline: false, model_based: false },
    AlgoInfo { name: "dqn", label: "DQN", baseline: false, model_based: false },
    AlgoInfo { name: "bc", label: "BC", baseline: true, model_based: false },
    AlgoInfo { name: "bcq", label: "BCQ", baseline: true, model_based: false },
    AlgoInfo { name: "dyna-cql", label: "Dyna-CQL", baseline: true, model_based: true },
];

/// An offline algorithm of [`ALGORITHMS`] (its index); written as its name.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct Algo(u8);

impl Algo {
    /// Conservative Q-learning, paper eq. 8: the paper's learner.
    pub const CQL: Algo = Algo(0);
    /// DQN on a fixed dataset, paper eq. 7: the baseline that overestimates.
    pub const DQN: Algo = Algo(1);

    /// Every registered algorithm, in order.
    pub fn all() -> impl Iterator<Item = Algo> {
        (0..ALGORITHMS.len()).map(|i| Algo(i as u8))
    }

    /// The algorithms registered as baselines: `learner.baselines`' default.
    pub fn baselines() -> Vec<Algo> {
        Algo::all()
            .filter(|a| ALGORITHMS[a.index()].baseline)
            .collect()
    }

    /// Its place in [`ALGORITHMS`].
    pub fn index(self) -> usize {
        usize::from(self.0)
    }

    pub fn name(self) -> &'static str {
        ALGORITHMS[self.index()].name
    }

    pub fn label(self) -> &'static str {
        ALGORITHMS[self.index()].label
    }

    /// Whether it learns from a model of the world as well as the shots.
    pub fn model_based(self) -> bool {
        ALGORITHMS[self.index()].model_based
    }
}

impl fmt::Display for Algo {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

impl std::str::FromStr for Algo {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        Algo::all().find(|a| a.name() == s).ok_or_else(|| {
            let names: Vec<String> = Algo::all().map(|a| format!("`{a}`")).collect();
            format!("`{s}`: expected one of {}", names.join(", "))
        })
    }
}

impl Serialize for Algo {
    fn serialize<S: Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.serialize_str(self.name())
    }
}

impl<'de> Deserialize<'de> for Algo {
    fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        let name = String::deserialize(d)?;
        name.parse().map_err(serde::de::Error::custom)
    }
}

/// Where a fine-tuned method's network starts.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum Start {
    /// A random init (the run's seed + 1).
    Random,
    /// MAML's meta-initialisation w0 (Algorithm 4), meta-trained with the same algorithm
    /// (`meta.inner_loss`): CQL-MAML, DQN-MAML.
    Maml,
    /// One network trained with the same algorithm (`meta.inner_loss`) on the union of the
    /// meta-train tasks' shots (`uavmeta_meta::pretrain`): the multi-task baseline that shows
    /// what MAML adds.
    Pretrain,
    /// The run's w0, meta-trained with another algorithm (`meta.inner_loss`): a baseline
    /// fine-tuned from the paper's init.
    W0,
    /// The context learner's task-conditioned network (`uavmeta_meta::context`), its task code
    /// read from the unseen task's shots: FOCAL-style context-based meta-RL, fine-tuned like w0.
    Context,
}

impl Start {
    const ALL: [Start; 5] = [
        Start::Random,
        Start::Maml,
        Start::Pretrain,
        Start::W0,
        Start::Context,
    ];

    /// What it adds to the algorithm's name (`cql`, `cql-maml`, `cql-pretrain`) and label.
    fn suffixes(self) -> (&'static str, &'static str) {
        match self {
            Start::Random => ("", ""),
            Start::Maml => ("-maml", "-MAML"),
            Start::Pretrain => ("-pretrain", "-pretrain"),
            Start::W0 => ("-w0", " from w0"),
            Start::Context => ("-context", "-context"),
        }
    }
}

/// A row of the tables: a network trained some way, or a reference.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum Method {
    /// MAML's meta-initialisation w0 after a meta-epoch (Algorithm 4), not adapted to a task.
    MetaInit,
    /// The online DQN agent that made a task's dataset (one checkpoint, epoch 1): the paper's
    /// "online" reference line.
    OnlineDqn,
    /// The context learner's task-conditioned network (`uavmeta_meta::context`), its task code
    /// read from an unseen task's shots, before any gradient step (one checkpoint per task,
    /// epoch 1): its zero-shot policy, where `cql-context` starts.
    ContextInit,
    /// `algo` fine-tuned on the few shots of an unseen task from `start`.
    FineTuned { algo: Algo, start: Start },
}

impl Method {
    /// CQL-MAML, the paper's method: w0 fine-tuned with CQL.
    pub const CQL_MAML: Method = Method::tuned(Algo::CQL, Start::Maml);
    /// CQL from a random initialisation: the paper's main baseline.
    pub const CQL: Method = Method::tuned(Algo::CQL, Start::Random);
    /// CQL pretrained on the meta-train tasks' shots, fine-tuned like CQL-MAML.
    pub const CQL_PRETRAIN: Method = Method::tuned(Algo::CQL, Start::Pretrain);
    /// CQL from the context learner's zero-shot policy, fine-tuned like CQL-MAML.
    pub const CQL_CONTEXT: Method = Method::tuned(Algo::CQL, Start::Context);
    /// DQN-MAML, the paper's ablation without the conservative term.
    pub const DQN_MAML: Method = Method::tuned(Algo::DQN, Start::Maml);
    /// Offline DQN from a random initialisation: DQN-MAML's baseline.
    pub const DQN: Method = Method::tuned(Algo::DQN, Start::Random);

    /// `algo` fine-tuned from `start`.
    pub const fn tuned(algo: Algo, start: Start) -> Method {
        Method::FineTuned { algo, start }
    }

    /// A MAML init meta-trained with `inner_loss`, fine-tuned with the same algorithm.
    pub fn maml(inner_loss: Algo) -> Method {
        Method::tuned(inner_loss, Start::Maml)
    }

    /// The methods a meta-learner fine-tunes on each meta-test task, in order: the inner loss
    /// from w0, from a random init, from its pretrained init and from the context learner's
    /// zero-shot policy, then each of `baselines`
    /// (`learner.baselines`; the inner loss is skipped there) from w0 and from a random init.
    pub fn fine_tuned(inner_loss: Algo, baselines: &[Algo]) -> Vec<Method> {
        let mut methods = vec![
            Method::tuned(inner_loss, Start::Maml),
            Method::tuned(inner_loss, Start::Random),
            Method::tuned(inner_loss, Start::Pretrain),
            Method::tuned(inner_loss, Start::Context),
        ];
        for &algo in baselines.iter().filter(|&&a| a != inner_loss) {
            methods.push(Method::tuned(algo, Start::W0));
            methods.push(Method::tuned(algo, Start::Random));
        }
        methods
    }

    /// The name used in file paths, metric labels and CSV rows.
    pub fn name(self) -> String {
        match self {
            Method::MetaInit => "maml-init".into(),
            Method::OnlineDqn => "online-dqn".into(),
            Method::ContextInit => "context-init".into(),
            Method::FineTuned { algo, start } => format!("{algo}{}", start.suffixes().0),
        }
    }

    /// The name in figures and tables, as the paper writes it.
    pub fn label(self) -> String {
        match self {
            Method::MetaInit => "maml-init".into(),
            Method::OnlineDqn => "online DQN".into(),
            Method::ContextInit => "context-init".into(),
            Method::FineTuned { algo, start } => {
                format!("{}{}", algo.label(), start.suffixes().1)
            }
        }
    }

    /// The algorithm it is fine-tuned with on an unseen task's shots; `None` for the three that
    /// are not fine-tuned (w0 alone, the context learner's zero-shot policy, the online agent).
    pub fn algo(self) -> Option<Algo> {
        match self {
            Method::FineTuned { algo, .. } => Some(algo),
            Method::MetaInit | Method::OnlineDqn | Method::ContextInit => None,
        }
    }

    /// Where it starts; `None` for the three that are not fine-tuned.
    pub fn start(self) -> Option<Start> {
        match self {
            Method::FineTuned { start, .. } => Some(start),
            Method::MetaInit | Method::OnlineDqn | Method::ContextInit => None,
        }
    }

    /// Its number on the wire: 0 to 2 for the three that are not fine-tuned, then
    /// 3 + start x 64 + algorithm.
    /// (`Start::Maml` and `Start::W0` of one algorithm load the same w0; the name tells which
    /// algorithm meta-trained it.)
    pub fn code(self) -> u32 {
        match self {
            Method::MetaInit => 0,
            Method::OnlineDqn => 1,
            Method::ContextInit => 2,
            Method::FineTuned { algo, start } => 3 + start as u32 * 64 + algo.index() as u32,
        }
    }

    pub fn from_code(code: u32) -> Option<Method> {
        match code {
            0 => Some(Method::MetaInit),
            1 => Some(Method::OnlineDqn),
            2 => Some(Method::ContextInit),
            _ => {
                let (start, algo) = ((code - 3) / 64, (code - 3) % 64);
                let start = *Start::ALL.get(start as usize)?;
                let algo = Algo::all().nth(algo as usize)?;
                Some(Method::tuned(algo, start))
            }
        }
    }

    /// The method a name gives ([`Method::name`]'s inverse).
    pub fn from_name(name: &str) -> Option<Method> {
        Method::all().find(|m| m.name() == name)
    }

    /// The learned rows of a results table, in its order: every algorithm that reads the shots
    /// alone from a random init, then from pretraining, from its own MAML w0, from the context
    /// learner and from another's w0, then w0 alone and the context learner's zero-shot policy,
    /// then the model-based algorithms ([`Algo::model_based`]) in the same order of starts.
    pub fn learners() -> impl Iterator<Item = Method> {
        let starts = [
            Start::Random,
            Start::Pretrain,
            Start::Maml,
            Start::Context,
            Start::W0,
        ];
        let tuned = move |model_based: bool| {
            starts.into_iter().flat_map(move |start| {
                Algo::all()
                    .filter(move |a| a.model_based() == model_based)
                    .map(move |algo| Method::tuned(algo, start))
            })
        };
        tuned(false)
            .chain([Method::MetaInit, Method::ContextInit])
            .chain(tuned(true))
    }

    /// Whether it learns from a model of the world as well as the shots: a row of the tables'
    /// model-based section.
    pub fn model_based(self) -> bool {
        self.algo().is_some_and(Algo::model_based)
    }

    /// The epoch of its network as the tables print it, one word: a fine-tuning epoch ("100"),
    /// a meta-epoch of w0 ("meta-150"), "zero-shot" for the context learner's policy before any
    /// gradient step and "-" for the online agent, which have one network each.
    pub fn network_label(self, epoch: u32) -> String {
        match self {
            Method::FineTuned { .. } => epoch.to_string(),
            Method::MetaInit => format!("meta-{epoch}"),
            Method::ContextInit => "zero-shot".into(),
            Method::OnlineDqn => "-".into(),
        }
    }

    /// Every method: the references, then each algorithm from each start.
    pub fn all() -> impl Iterator<Item = Method> {
        let tuned = Algo::all().flat_map(|algo| {
            Start::ALL
                .into_iter()
                .map(move |start| Method::tuned(algo, start))
        });
        [Method::MetaInit, Method::OnlineDqn, Method::ContextInit]
            .into_iter()
            .chain(tuned)
    }
}

impl fmt::Display for Method {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.name())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_method_has_its_own_name_and_code_and_both_read_back() {
        let all: Vec<Method> = Method::all().collect();
        assert_eq!(all.len(), 3 + 5 * ALGORITHMS.len());
        for m in &all {
            assert_eq!(Method::from_code(m.code()), Some(*m), "{m}");
            assert_eq!(Method::from_name(&m.name()), Some(*m), "{m}");
            assert_eq!(
                all.iter().filter(|o| o.name() == m.name()).count(),
                1,
                "{m}"
            );
        }
        assert_eq!(Method::from_code(3 + 5 * 64), None);
        assert_eq!(Method::from_code(3 + ALGORITHMS.len() as u32), None);
        assert_eq!(Method::CQL_MAML.name(), "cql-maml");
        assert_eq!(Method::CQL_PRETRAIN.label(), "CQL-pretrain");
    }

    #[test]
    fn an_unknown_algorithm_is_refused_with_the_registered_names() {
        let error = "ppo".parse::<Algo>().unwrap_err();
        assert!(
            error.contains("`ppo`") && error.contains("`cql`, `dqn`"),
            "{error}"
        );
        assert_eq!("dqn".parse::<Algo>(), Ok(Algo::DQN));
    }
}
