//! A model-based algorithm's model rows: transitions of the policy being trained, rolled out in
//! the world its shots identify, added to each epoch's shots (`learner.model_rows`,
//! `learner.model_epsilon`; `dyna-cql`, docs/MODEL.md section 5).
//!
//! 500 shots cover a few hundred of the states a fine-tuned policy visits, and where the data
//! lacks a state the conservative term holds the policy near the behaviour that made the shots.
//! The shots also identify the world (`uavmeta_world::identify`: told the world's form, it fits
//! each device's power cost), so before each epoch the network acts epsilon-greedily in that
//! world from the shots' own states, and `learner.model_rows` of the steps, drawn at random, join
//! the shots, as Dyna and MBPO add model rollouts to the real data. Their rewards come from the
//! model, never the true world. The algorithm's own per-transition terms (CQL's conservative
//! term) average over the batch with the model rows weighing 0, so they anchor only to what the
//! data did. Where the shots identify no world (they show rain) there are no model rows and the
//! run trains on the shots alone.

use rand::seq::SliceRandom;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use uavmeta_proto::config::WorldConfig;

use crate::algorithm;
use crate::qnet::QNetwork;
use crate::train::{EvaluatePolicy, Rollouts, TrainOptions};
use crate::transitions::Transitions;

/// The model rows of one training run.
pub struct ModelRows {
    rows: usize,
    epsilon: f64,
    seed: u64,
    world: WorldConfig,
    reward_scale: f64,
    /// The first epoch's rows, drawn when the run starts to learn whether the world is known.
    first: Option<Transitions>,
    /// The last epoch's rows.
    last: Option<Transitions>,
}

impl ModelRows {
    /// The model rows of a run with `opts` starting from `q`, or `None`: the algorithm is not
    /// model-based, `learner.model_rows` is 0, or the shots identify no world.
    pub fn new(
        opts: &TrainOptions,
        q: &QNetwork,
        evaluator: &mut dyn EvaluatePolicy,
    ) -> Option<Self> {
        let cfg = &opts.config.learner;
        if cfg.model_rows == 0 || !algorithm::of(opts.algorithm).model_rows() {
            return None;
        }
        let mut model = Self {
            rows: cfg.model_rows,
            epsilon: cfg.model_epsilon,
            seed: opts.seed,
            world: opts.config.world.clone(),
            reward_scale: cfg.reward_scale,
            first: None,
            last: None,
        };
        let Some(first) = model.draw(1, q, evaluator) else {
            tracing::warn!(
                algorithm = %opts.algorithm,
                "the shots identify no world (they show rain, or are not this world's steps): \
                 no model rows, the run trains on the shots alone"
            );
            return None;
        };
        // Fewer steps than asked for where the rollouts hold fewer (the horizon ends branches).
        model.rows = first.len();
        model.first = Some(first);
        Some(model)
    }

    /// Rows per epoch.
    pub fn rows(&self) -> usize {
        self.rows
    }

    /// Epoch `epoch`'s data: `shots`, then `rows()` steps of `q` in the identified world (the
    /// previous epoch's again should the evaluator stop answering, which none does).
    pub fn epoch_data(
        &mut self,
        epoch: usize,
        q: &QNetwork,
        shots: &Transitions,
        evaluator: &mut dyn EvaluatePolicy,
    ) -> Transitions {
        let drawn = match self.first.take() {
            Some(first) => Some(first),
            None => self.draw(epoch, q, evaluator),
        };
        if let Some(drawn) = drawn.filter(|d| d.len() == self.rows) {
            self.last = Some(drawn);
        }
        let model = self
            .last
            .as_ref()
            .expect("the first epoch's rows are drawn");
        Transitions::concat([shots, model])
    }

    /// `rows` of epoch `epoch`'s rollouts of `q`, drawn without replacement.
    fn draw(
        &self,
        epoch: usize,
        q: &QNetwork,
        evaluator: &mut dyn EvaluatePolicy,
    ) -> Option<Transitions> {
        let epoch = epoch as u64;
        let rollout_seed = self.seed.wrapping_mul(1_000_003).wrapping_add(epoch);
        let ask = Rollouts {
            rows: self.rows,
            epsilon: self.epsilon,
            seed: rollout_seed,
        };
        let mut steps = evaluator.rollouts(q, ask)?;
        let order_seed = self.seed.wrapping_mul(7919).wrapping_add(epoch);
        steps.shuffle(&mut ChaCha8Rng::seed_from_u64(order_seed));
        steps.truncate(self.rows);
        Transitions::new(&steps, &self.world, self.reward_scale).ok()
    }
}
