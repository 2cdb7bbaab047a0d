//! Online DQN (docs/MODEL.md sections 4-5): the paper's behaviour policy, whose replay buffer is
//! sampled for the offline datasets, and its "online" reference line.
//!
//! Settings: `[collect.dqn]` (its budget, buffer, exploration schedule, network, rate and
//! stabilisers; `proto::config::OnlineDqnConfig`) and `[learner]`'s `gamma`, `reward_scale` and
//! `batch_size`, so the online agent and the offline learners see the same rewards.
//!
//! The paper gives no settings for this agent; docs/MODEL.md section 5 asks for what a practitioner
//! would use. The defaults are the usual DQN stabilisers: Double DQN, the Huber loss, gradient-norm
//! clipping at 10, a target network refreshed every 2 000 gradient steps, the paper's [256, 256]
//! network and Adam at 2e-4. Without them the agent swings between heuristic level and far below
//! random from one evaluation to the next (docs/EXPERIMENTS.md).
//!
//! Loop, per environment step: epsilon-greedy action (uniform random during the first
//! `learning_starts` steps, then epsilon falls linearly from `eps_start` to `eps_end` over
//! `eps_decay_steps`), store the transition, and every `train_every` steps one Adam step on
//! eq. 7 over a uniform minibatch of the buffer. Time limits are not terminal: the last
//! transition of an episode is stored with `truncated = true` and still bootstraps.
//!
//! Snapshot selection (`select_every` > 0): once epsilon is at its floor, every
//! `select_every` steps and at the last step the greedy policy is evaluated exactly on the
//! agent's own task, and the best one is kept as the agent's policy. It only reads the network:
//! training, the replay buffer and the dataset are the same with or without it.

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use tch::Tensor;
use uavmeta_learner::dqn::{Bootstrap, Dqn, TdConfig};
use uavmeta_learner::optim::{clip_grad_norm, FusedAdam};
use uavmeta_learner::qnet::{QNetwork, QNetworkConfig};
use uavmeta_learner::train::EvaluatePolicy;
use uavmeta_learner::transitions::{Transitions, TransitionsError};
use uavmeta_proto::config::{Config, LearnerConfig, OnlineDqnConfig, TaskConfig, WorldConfig};
use uavmeta_proto::dataset::Transition;

use crate::policy::q_policy::{Evaluator, QPolicy};
use uavmeta_world::rollout::Policy;
use uavmeta_world::world::World;

/// A fixed-capacity FIFO of transitions: once full, each new transition replaces the oldest.
#[derive(Debug, Clone)]
pub struct ReplayBuffer {
    items: Vec<Transition>,
    capacity: usize,
    /// Where the next transition goes once the buffer is full (the oldest one's slot).
    next: usize,
}

impl ReplayBuffer {
    pub fn new(capacity: usize) -> Self {
        Self {
            items: Vec::with_capacity(capacity),
            capacity,
            next: 0,
        }
    }

    pub fn push(&mut self, t: Transition) {
        if self.items.len() < self.capacity {
            self.items.push(t);
        } else {
            self.items[self.next] = t;
            self.next = (self.next + 1) % self.capacity;
        }
    }

    pub fn len(&self) -> usize {
        self.items.len()
    }

    pub fn is_empty(&self) -> bool {
        self.items.is_empty()
    }

    pub fn capacity(&self) -> usize {
        self.capacity
    }

    /// The stored transitions, oldest first.
    pub fn iter(&self) -> impl Iterator<Item = &Transition> {
        let (newer, older) = self.items.split_at(self.next);
        older.iter().chain(newer)
    }

    /// `n` transitions drawn uniformly with replacement.
    fn sample<'a>(&'a self, rng: &mut ChaCha8Rng, n: usize) -> Vec<&'a Transition> {
        (0..n)
            .map(|_| &self.items[rng.random_range(0..self.items.len())])
            .collect()
    }
}

/// Episodes behind [`OnlineDqn::recent_return`]: one return is noise, the mean of 20 a trend.
pub const RECENT_EPISODES: usize = 20;

/// One online DQN agent training in one task's world.
pub struct OnlineDqn {
    // Settings: `[collect.dqn]`, `[learner]` (gamma, reward scale, minibatch), the world, and the
    // TD loss it trains on (eq. 7 with `[collect.dqn]`'s stabilisers).
    dqn: OnlineDqnConfig,
    learner: LearnerConfig,
    world_config: WorldConfig,
    td: TdConfig,
    // Its network, target network and optimiser.
    q: QNetwork,
    target: QNetwork,
    opt: FusedAdam,
    gradient_steps: usize,
    // Its world, exploration stream and replay buffer.
    world: World,
    replay: ReplayBuffer,
    rng: ChaCha8Rng,
    task: u32,
    actor: u32,
    /// Environment steps taken.
    steps: usize,
    episode: u64,
    /// Return of the episode in progress.
    episode_return: f64,
    /// Returns of every finished episode, in order.
    returns: Vec<f64>,
    // Snapshot selection: the episodes it scores a policy on, the best snapshot so far
    // (`select_every` > 0) and every evaluation as (environment step, return).
    selector: Evaluator,
    best: Option<QNetwork>,
    evaluations: Vec<(usize, f64)>,
}

impl OnlineDqn {
    /// An untrained agent for task `task` (index `task_id` in the config's `[[tasks]]`), acting as
    /// actor `actor`. Its network, world, exploration and selection episodes all derive from
    /// `seed`, drawn in an order fixed once and for all.
    pub fn new(config: &Config, task: &TaskConfig, task_id: u32, actor: u32, seed: u64) -> Self {
        let (dqn, w) = (&config.collect.dqn, &config.world);
        let mut seeds = ChaCha8Rng::seed_from_u64(seed);
        let q = QNetworkConfig::for_world(w, &dqn.hidden).init(seeds.random());
        let world = World::new(w, task, seeds.random());
        let rng = ChaCha8Rng::seed_from_u64(seeds.random());
        // Drawn last, so that the draws above are those of an agent without selection.
        let selector = Evaluator::new(w, task, config.learner.eval_episodes, seeds.random());
        Self {
            dqn: dqn.clone(),
            learner: config.learner.clone(),
            world_config: w.clone(),
            td: TdConfig {
                gamma: config.learner.gamma,
                bootstrap: Bootstrap::double_if(dqn.double_dqn),
                huber: dqn.huber,
            },
            target: q.duplicate(),
            opt: FusedAdam::new(q.parameters(), dqn.lr),
            q,
            gradient_steps: 0,
            world,
            replay: ReplayBuffer::new(dqn.replay_capacity),
            rng,
            task: task_id,
            actor,
            steps: 0,
            episode: 0,
            episode_return: 0.0,
            returns: Vec::new(),
            selector,
            best: None,
            evaluations: Vec::new(),
        }
    }

    /// Trains for `collect.dqn.steps` environment steps.
    pub fn train(&mut self) -> Result<(), TransitionsError> {
        self.train_steps(self.dqn.steps)
    }

    /// Trains for `steps` more environment steps, logging the recent return every
    /// [`RECENT_EPISODES`] episodes.
    pub fn train_steps(&mut self, steps: usize) -> Result<(), TransitionsError> {
        for _ in 0..steps {
            let finished = self.step()?;
            self.log_progress(finished);
        }
        Ok(())
    }

    /// One environment step (and the gradient step it is due); the episode's return when the step
    /// ended an episode.
    pub fn step(&mut self) -> Result<Option<f64>, TransitionsError> {
        // ALGO: epsilon-greedy behaviour.
        let action = match self.rng.random_bool(self.epsilon()) {
            true => self.rng.random_range(0..self.world.layout().action_count()),
            false => QPolicy::new(&self.q).act(&self.world),
        };
        let finished = self.advance(action);
        let c = &self.dqn;
        if self.steps >= c.learning_starts && self.steps.is_multiple_of(c.train_every) {
            self.gradient_step()?;
        }
        if self.selection_due() {
            self.select();
        }
        Ok(finished)
    }

    /// ALGO: one Adam step on eq. 7 (with the configured stabilisers) over a uniform minibatch of
    /// the replay buffer.
    fn gradient_step(&mut self) -> Result<(), TransitionsError> {
        self.opt.set_lr(self.learning_rate());
        let sample = self.replay.sample(&mut self.rng, self.learner.batch_size);
        let mb = Transitions::new(&sample, &self.world_config, self.learner.reward_scale)?;
        let q_all = self.q.forward(&mb.obs); // [B, A]
        let target = |s: &Tensor| self.target.forward(s);
        let online = |s: &Tensor| self.q.forward(s);
        let loss = self
            .td
            .td_errors((&Dqn, &self.learner), &q_all, &mb, target, online)
            .mean(None); // eq. 7
        self.opt.zero_grad();
        loss.backward();
        if self.dqn.grad_clip_norm > 0.0 {
            clip_grad_norm(&self.q.parameters(), self.dqn.grad_clip_norm);
        }
        self.opt.step();
        self.gradient_steps += 1;
        if self
            .gradient_steps
            .is_multiple_of(self.dqn.target_update_every)
        {
            self.target.copy_from(&self.q);
        }
        Ok(())
    }

    /// Takes `action`, stores the transition and, at the horizon, starts the next episode;
    /// returns the finished episode's return.
    fn advance(&mut self, action: usize) -> Option<f64> {
        let obs = self.world.observation().to_vec();
        let step_index = self.world.t();
        let step = self.world.step(action);
        self.replay.push(Transition {
            task: self.task,
            actor: self.actor,
            episode: self.episode,
            step: step_index,
            seq: self.steps as u64,
            obs,
            action: action as u16,
            reward: step.reward as f32,
            next_obs: self.world.observation().to_vec(),
            truncated: step.truncated,
        });
        self.steps += 1;
        self.episode_return += step.reward;
        if !step.truncated {
            return None;
        }
        let finished = self.episode_return;
        self.returns.push(finished);
        self.episode += 1;
        self.episode_return = 0.0;
        self.world.reset();
        Some(finished)
    }

    /// The exploration rate of the next step: uniform random during the first `learning_starts`
    /// steps, then linear from `eps_start` to `eps_end` over `eps_decay_steps`.
    pub fn epsilon(&self) -> f64 {
        let c = &self.dqn;
        if self.steps < c.learning_starts {
            return 1.0;
        }
        let progress = match c.eps_decay_steps {
            0 => 1.0,
            n => ((self.steps - c.learning_starts) as f64 / n as f64).min(1.0),
        };
        c.eps_start + (c.eps_end - c.eps_start) * progress
    }

    /// The learning rate of the next gradient step: `lr`, falling linearly to
    /// `lr * lr_final_fraction` between `learning_starts` and `steps`.
    pub fn learning_rate(&self) -> f64 {
        let c = &self.dqn;
        let span = c.steps.saturating_sub(c.learning_starts).max(1);
        let progress = (self.steps.saturating_sub(c.learning_starts) as f64 / span as f64).min(1.0);
        c.lr * (1.0 - (1.0 - c.lr_final_fraction) * progress)
    }

    /// Whether a selection evaluation is due now: every `select_every` steps once epsilon is at
    /// its floor, and at the last of `steps`.
    fn selection_due(&self) -> bool {
        let c = &self.dqn;
        c.select_every > 0
            && (self.steps == c.steps
                || (self.steps >= c.learning_starts + c.eps_decay_steps
                    && self.steps.is_multiple_of(c.select_every)))
    }

    /// Scores the live network's greedy policy and keeps it if it beats the best snapshot (the
    /// earlier one on a tie).
    fn select(&mut self) {
        let ret = self.selector.evaluate(&self.q).ret.mean;
        let better = self.selected().is_none_or(|(_, best)| ret > best);
        self.evaluations.push((self.steps, ret));
        match (&mut self.best, better) {
            (_, false) => {}
            (Some(best), true) => best.copy_from(&self.q),
            (None, true) => self.best = Some(self.q.duplicate()),
        }
    }

    /// Logs the recent return every [`RECENT_EPISODES`] episodes, after an episode `finished`.
    fn log_progress(&self, finished: Option<f64>) {
        if finished.is_some() && self.returns.len().is_multiple_of(RECENT_EPISODES) {
            tracing::info!(
                task = self.task,
                actor = self.actor,
                steps = self.steps,
                episodes = self.returns.len(),
                epsilon = self.epsilon(),
                mean_return = self.recent_return(),
                "online DQN"
            );
        }
    }

    /// Mean return of the last [`RECENT_EPISODES`] finished episodes (of all of them while fewer
    /// have finished); `None` before the first.
    pub fn recent_return(&self) -> Option<f64> {
        let recent = &self.returns[self.returns.len().saturating_sub(RECENT_EPISODES)..];
        (!recent.is_empty()).then(|| recent.iter().sum::<f64>() / recent.len() as f64)
    }

    /// The step and evaluated return of the snapshot selection has kept so far (the first of the
    /// best), if any.
    pub fn selected(&self) -> Option<(usize, f64)> {
        (self.evaluations.iter().copied()).reduce(|best, e| if e.1 > best.1 { e } else { best })
    }

    /// Every selection evaluation so far, (environment step, return), in order; the last one is
    /// the live network's at that step.
    pub fn selection_evaluations(&self) -> &[(usize, f64)] {
        &self.evaluations
    }

    /// The agent's Q-network, whose greedy policy ([`QPolicy`]) is the "online DQN" reference:
    /// the best snapshot when selection is on and has run, else the network being trained.
    pub fn q_network(&self) -> &QNetwork {
        self.best.as_ref().unwrap_or(&self.q)
    }

    /// The replay buffer, from which the paper's offline dataset of this task is sampled.
    pub fn replay_buffer(&self) -> &ReplayBuffer {
        &self.replay
    }

    /// Returns of the finished training episodes, in order.
    pub fn episode_returns(&self) -> &[f64] {
        &self.returns
    }

    /// Environment steps taken so far.
    pub fn steps(&self) -> usize {
        self.steps
    }

    /// The task index and the actor number its transitions carry.
    pub fn task_and_actor(&self) -> (u32, u32) {
        (self.task, self.actor)
    }
}
