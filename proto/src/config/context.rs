//! `[context]`: the task-inferring learner of docs/MODEL.md section 5 (context-based offline
//! meta-RL after FOCAL). Read by `uavmeta_meta::context`.

use garde::Validate;
use serde::{Deserialize, Serialize};
use smart_default::SmartDefault;

use super::rules::{at_least, widths, within};

/// The task encoder and the task-conditioned Q-network of the context learner
/// (`uavmeta_meta::context`): the encoder reads a set of a task's transitions and writes a task
/// code z, the Q-network acts on the observation and z.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, SmartDefault, Validate)]
#[serde(deny_unknown_fields, default)]
#[garde(allow_unvalidated)]
pub struct ContextConfig {
    /// d, the task code's length: the values the Q-network reads beside the observation.
    #[default(8)]
    #[garde(custom(within(1..=64, "a code length from 1 to 64")))]
    pub latent: usize,
    /// Hidden layer widths of the encoder's MLP over one transition (s, a, r, s').
    #[default(vec![64, 64])]
    #[garde(custom(widths()))]
    pub encoder_hidden: Vec<usize>,
    /// Transitions of one context while training: the set a task code is pooled over. At
    /// meta-test the code is pooled over every shot.
    #[default(64)]
    #[garde(custom(at_least(1)))]
    pub transitions_per_context: usize,
    /// Adam steps (`learner.lr`) of the encoder, learning to read the meta-train tasks'
    /// parameters from their contexts, before the Q-network trains.
    #[default(2000)]
    #[garde(custom(at_least(1)))]
    pub encoder_steps: usize,
}
