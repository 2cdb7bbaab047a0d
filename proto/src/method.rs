//! Which method made a checkpoint, a table row or a curve: one vocabulary for checkpoints, the
//! evaluator's metrics, `launch`'s table, `reproduce`'s figures and the CLI. Each method says its
//! name (files, metrics, CSV), its label (figures), the loss it is fine-tuned with and how its
//! starting network is trained.

use std::fmt;

use crate::config::Loss;

/// The method that trained a checkpoint; `u32` on the wire.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum Method {
    /// MAML's meta-initialisation w0 after a meta-epoch (Algorithm 4), not adapted to a task.
    MetaInit,
    /// w0 fine-tuned with CQL on the few shots of an unseen task: the paper's method.
    CqlMaml,
    /// CQL from a random initialisation on the same shots: the paper's main baseline.
    Cql,
    /// CQL pretrained on the union of the meta-train tasks' shots, fine-tuned like CQL-MAML: the
    /// multi-task baseline that shows what MAML adds.
    CqlPretrain,
    /// The online DQN agent that made a task's dataset (one checkpoint, epoch 1): the paper's
    /// "online" reference line.
    OnlineDqn,
    /// A DQN-MAML w0 (`meta.inner_loss = "dqn"`) fine-tuned with offline DQN (eq. 7): the paper's
    /// ablation without the conservative term.
    DqnMaml,
    /// Offline DQN from a random initialisation on the same shots: DQN-MAML's baseline.
    Dqn,
}

impl Method {
    pub const ALL: [Method; 7] = [
        Method::MetaInit,
        Method::CqlMaml,
        Method::Cql,
        Method::CqlPretrain,
        Method::OnlineDqn,
        Method::DqnMaml,
        Method::Dqn,
    ];

    /// The five methods fine-tuned on an unseen task's shots, as the paper's figures list them.
    pub const FINE_TUNED: [Method; 5] = [
        Method::CqlMaml,
        Method::CqlPretrain,
        Method::Cql,
        Method::Dqn,
        Method::DqnMaml,
    ];

    /// The CQL fine-tunings from the three inits every figure that compares inits shows.
    pub const CQL_INITS: [Method; 3] = [Method::CqlMaml, Method::CqlPretrain, Method::Cql];

    /// A MAML init of this inner loss, fine-tuned with the same loss.
    pub fn maml(inner_loss: Loss) -> Method {
        match inner_loss {
            Loss::Cql => Method::CqlMaml,
            Loss::Dqn => Method::DqnMaml,
        }
    }

    /// The methods a meta-learner fine-tunes on each meta-test task, in order: the MAML init,
    /// the same loss from a random init and, for CQL, the multi-task pretrained init.
    pub fn fine_tuned(inner_loss: Loss) -> &'static [Method] {
        match inner_loss {
            Loss::Cql => &[Method::CqlMaml, Method::Cql, Method::CqlPretrain],
            Loss::Dqn => &[Method::DqnMaml, Method::Dqn],
        }
    }

    /// The name used in file paths, metric labels and CSV rows.
    pub fn name(self) -> &'static str {
        match self {
            Method::MetaInit => "maml-init",
            Method::CqlMaml => "cql-maml",
            Method::Cql => "cql",
            Method::CqlPretrain => "cql-pretrain",
            Method::OnlineDqn => "online-dqn",
            Method::DqnMaml => "dqn-maml",
            Method::Dqn => "dqn",
        }
    }

    /// The name in figures and tables, as the paper writes it.
    pub fn label(self) -> &'static str {
        match self {
            Method::MetaInit => "maml-init",
            Method::CqlMaml => "CQL-MAML",
            Method::Cql => "CQL",
            Method::CqlPretrain => "CQL-pretrain",
            Method::OnlineDqn => "online DQN",
            Method::DqnMaml => "DQN-MAML",
            Method::Dqn => "DQN",
        }
    }

    /// The loss it is fine-tuned with on an unseen task's shots; `None` for the two that are not
    /// fine-tuned (w0 alone, the online agent).
    pub fn loss(self) -> Option<Loss> {
        match self {
            Method::CqlMaml | Method::Cql | Method::CqlPretrain => Some(Loss::Cql),
            Method::DqnMaml | Method::Dqn => Some(Loss::Dqn),
            Method::MetaInit | Method::OnlineDqn => None,
        }
    }

    /// How its starting network is trained on the meta-train tasks; `None` for a random one (and
    /// for the online agent, which trains on its own task).
    pub fn init(self) -> Option<Init> {
        match self {
            Method::CqlMaml | Method::MetaInit => Some(Init::Maml(Loss::Cql)),
            Method::DqnMaml => Some(Init::Maml(Loss::Dqn)),
            Method::CqlPretrain => Some(Init::Pretrain),
            Method::Cql | Method::Dqn | Method::OnlineDqn => None,
        }
    }

    /// Its number on the wire.
    pub fn code(self) -> u32 {
        self as u32
    }

    pub fn from_code(code: u32) -> Option<Method> {
        Self::ALL.into_iter().find(|m| m.code() == code)
    }
}

impl fmt::Display for Method {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

/// How a method's starting network is trained on the meta-train tasks.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Init {
    /// MAML (Algorithm 4) with this inner loss: w0.
    Maml(Loss),
    /// CQL on the union of the meta-train tasks' shots (`uavmeta_meta::pretrain`).
    Pretrain,
}

impl Init {
    /// The name of the checkpoints it makes: the method fine-tuned from it.
    pub fn name(self) -> &'static str {
        match self {
            Init::Maml(loss) => Method::maml(loss).name(),
            Init::Pretrain => Method::CqlPretrain.name(),
        }
    }
}
