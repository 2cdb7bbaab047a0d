//! Fitted Q evaluation (FQE; Le, Voloshin & Yue 2019, d3rlpy's `FQE`): the value of a fixed greedy
//! policy from offline transitions alone, with no step in the world.
//!
//! For the policy `pi(s) = argmax_a Q_pi(s, a)` of a trained network, a fresh network `F` is fitted
//! to the Bellman equation of `pi` (not of the optimal policy, as eq. 7 is):
//!
//! ```text
//! L_FQE(F) = mean_batch ( r + gamma * Fhat(s', pi(s')) - F(s, a) )^2
//! ```
//!
//! with `Fhat` a target copy of `F` refreshed every `learner.fqe_target_update_every` steps, the same
//! TD form (squared or Huber) as the learner's. The estimate is `mean_s F(s, pi(s))` over the
//! data's states, in reward units: the value the data's states have under `pi`. Two policies
//! fitted on the same shots are ranked by it: the fine-tuning's selection (`learner.select_every`,
//! [`crate::train`]) keeps the network that scores best, the init included, so a run that
//! drifts below where it started can be caught without the world.
//!
//! With `learner.fqe_alpha` > 0 the fit adds eq. 8's conservative term on `F`, so actions the data
//! never took are valued below those it did (plain FQE extrapolates into them).
//!
//! The network starts from a fixed seed, whatever the policy, with its output bias at the data's
//! value scale `V_data = mean(r) / (1 - gamma)` (the value guard's), so the iterations start at
//! the right level and spend their steps on how `pi`'s value differs from it.

use std::path::Path;

use uavmeta_proto::config::LearnerConfig;

use crate::batch::Batch;
use crate::cql::{conservative_term, eq8};
use crate::dqn::td_errors;
use crate::optim::FusedAdam;
use crate::progress::{CsvError, CsvLog};
use crate::qnet::QNetwork;
use crate::train::{EvaluatePolicy, MinibatchOrder};

/// The FQE estimate of `policy`'s greedy policy on `data`: `mean_s F(s, pi(s))` in reward units
/// (divided back by `learner.reward_scale`), after `learner.fqe_steps` Adam(`learner.fqe_lr`)
/// steps on minibatches of `learner.batch` rows drawn in `seed`'s order.
pub fn fqe_value(policy: &QNetwork, data: &Batch, cfg: &LearnerConfig, seed: u64) -> f64 {
    // pi(s') of every transition and pi(s) of every state, once: the policy is fixed.
    let next_actions = policy.greedy(&data.next_obs).unsqueeze(-1); // [N, 1]
    let actions = policy.greedy(&data.obs).unsqueeze(-1); // [N, 1]
    let f = start_network(policy, data, cfg, seed);
    let mut target = f.duplicate();
    let mut opt = FusedAdam::new(f.parameters(), cfg.fqe_lr);
    let mut order = MinibatchOrder::new(data.len(), cfg.batch.min(data.len()), seed);
    for step in 1..=cfg.fqe_steps {
        let index = order.next_indices();
        let mb = data.select(&index);
        // V_pi(s') = Fhat(s', pi(s')), without a graph.
        let next_v = tch::no_grad(|| {
            target
                .forward(&mb.next_obs)
                .gather(-1, &next_actions.index_select(0, &index), false)
                .squeeze_dim(-1)
        });
        let f_all = f.forward(&mb.obs);
        let td = td_errors(&f_all, &next_v, &mb, cfg.gamma, cfg.huber).mean(None);
        let loss = eq8(&td, &conservative_term(&f_all, &mb), cfg.fqe_alpha);
        opt.backward_step(&loss);
        if step.is_multiple_of(cfg.fqe_target_update_every) {
            target.copy_from(&f);
        }
    }
    let v = tch::no_grad(|| f.forward(&data.obs).gather(-1, &actions, false).mean(None));
    v.double_value(&[]) / cfg.reward_scale
}

/// `F`'s start: `policy`'s architecture initialised from `seed`, its output bias set to
/// `V_data` (scaled) on every action (with gamma capped at 0.999, so an undiscounted run starts
/// at a finite level).
fn start_network(policy: &QNetwork, data: &Batch, cfg: &LearnerConfig, seed: u64) -> QNetwork {
    let f = policy.config().init(seed);
    let v_data = data.value_scale(cfg.gamma.min(0.999));
    let mut params = f.parameters();
    tch::no_grad(|| {
        let _ = params
            .last_mut()
            .expect("a network has layers")
            .fill_(v_data);
    });
    f
}

/// The fine-tuning's selection (`learner.select_every`): the init, every `select_every`-th and
/// the last epoch's published network scored by [`fqe_value`] on the run's shots, the best kept
/// (the earliest of equal scores: two networks with the same greedy actions score the same).
pub(crate) struct Selection {
    every: usize,
    seed: u64,
    /// The best so far: its score, epoch and network.
    best: Option<(f64, usize, QNetwork)>,
    csv: Option<CsvLog>,
}

const SELECT_CSV_HEADER: &str = "epoch,fqe_value,return,kept";

impl Selection {
    /// The selection of a run (`None` when `learner.select_every` is 0), with the init scored
    /// as epoch 0; `evaluator` measures each candidate for `select.csv` only
    /// ([`EvaluatePolicy::measure`]), never for the choice.
    pub(crate) fn new(
        cfg: &LearnerConfig,
        init: &QNetwork,
        data: &Batch,
        seed: u64,
        out_dir: Option<&Path>,
        evaluator: &mut dyn EvaluatePolicy,
    ) -> Result<Option<Self>, CsvError> {
        if cfg.select_every == 0 {
            return Ok(None);
        }
        let csv = match out_dir {
            Some(dir) => Some(CsvLog::create(&dir.join("select.csv"), SELECT_CSV_HEADER)?),
            None => None,
        };
        let mut selection = Self {
            every: cfg.select_every,
            seed,
            best: None,
            csv,
        };
        selection.score(0, init, data, cfg, evaluator)?;
        Ok(Some(selection))
    }

    /// After `epoch`: scores `published` if the epoch is a multiple of `select_every` or the
    /// run's last (so the trained network is always a candidate, whatever `select_every`).
    pub(crate) fn after_epoch(
        &mut self,
        epoch: usize,
        published: &QNetwork,
        data: &Batch,
        cfg: &LearnerConfig,
        evaluator: &mut dyn EvaluatePolicy,
    ) -> Result<(), CsvError> {
        if epoch.is_multiple_of(self.every) || epoch == cfg.epochs {
            self.score(epoch, published, data, cfg, evaluator)?;
        }
        Ok(())
    }

    /// The network the run publishes so far: the best-scoring one.
    pub(crate) fn published(&self) -> &QNetwork {
        &self.best.as_ref().expect("the init is always scored").2
    }

    fn score(
        &mut self,
        epoch: usize,
        q: &QNetwork,
        data: &Batch,
        cfg: &LearnerConfig,
        evaluator: &mut dyn EvaluatePolicy,
    ) -> Result<(), CsvError> {
        let value = fqe_value(q, data, cfg, self.seed);
        let kept = self.best.as_ref().is_none_or(|(best, _, _)| value > *best);
        if kept {
            self.best = Some((value, epoch, q.duplicate()));
        }
        if let Some(csv) = &mut self.csv {
            // The measured return, where the evaluator can give one without effects.
            let measured = evaluator
                .measure(q)
                .map_or(String::new(), |m| m.ret.mean.to_string());
            csv.line(&format!("{epoch},{value},{measured},{}", u8::from(kept)))?;
        }
        Ok(())
    }

    /// At the end: `q` becomes the best-scoring network; returns its epoch.
    pub(crate) fn publish_into(self, q: &mut QNetwork) -> usize {
        let (_, epoch, best) = self.best.expect("the init is always scored");
        q.copy_from(&best);
        epoch
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::qnet::QNetworkConfig;
    use tch::Tensor;

    /// A two-state chain, one input (the state, 0 or 1), two actions. Action 0 costs 1 and action
    /// 1 costs 0 from either state; every transition leads to the same state. A policy that
    /// takes action 1 has value 0; one that takes action 0 has -1 / (1 - gamma).
    fn chain() -> Batch {
        let obs = Tensor::from_slice(&[0.0f32, 0.0, 1.0, 1.0]).view([4, 1]);
        Batch {
            next_obs: obs.shallow_clone(),
            obs,
            actions: Tensor::from_slice(&[0i64, 1, 0, 1]),
            rewards: Tensor::from_slice(&[-1.0f32, 0.0, -1.0, 0.0]),
        }
    }

    /// A policy network that prefers `action` everywhere.
    fn prefers(action: usize) -> QNetwork {
        let mut bias = [0.0f32; 2];
        bias[action] = 1.0;
        QNetworkConfig::new(1, 2, &[8]).constant(&bias)
    }

    #[test]
    fn fqe_values_each_policy_by_its_own_actions() {
        let cfg = LearnerConfig {
            hidden: vec![8],
            gamma: 0.5,
            reward_scale: 1.0,
            batch: 4,
            fqe_lr: 1e-2,
            fqe_target_update_every: 20,
            fqe_steps: 3000,
            fqe_alpha: 0.0,
            ..LearnerConfig::default()
        };
        let data = chain();
        let free = fqe_value(&prefers(1), &data, &cfg, 0);
        let costly = fqe_value(&prefers(0), &data, &cfg, 0);
        // V = 0 and -1 / (1 - 0.5) = -2.
        assert!(free.abs() < 0.05, "the free action's value: {free}");
        assert!(
            (costly + 2.0).abs() < 0.05,
            "the costly action's value: {costly}"
        );
    }
}
