//! Online DQN (SPEC sections 4-5): the paper's behaviour policy, whose replay buffer is sampled
//! for the offline datasets, and its "online" reference line.
//!
//! Settings: the `[collect]` section (`dqn_steps`, `replay_capacity`, `learning_starts`,
//! `train_every`, `eps_start`, `eps_end`, `eps_decay_steps`, its network `dqn_hidden` and rate
//! `dqn_lr`, and the stabilisers `dqn_double`, `dqn_huber`, `dqn_grad_clip_norm`,
//! `dqn_target_update_every`, the n-step return `dqn_n_step`, the learning-rate schedule
//! `dqn_lr_final_fraction` and the snapshot selection `dqn_select_every`) and `[learner]`'s
//! `gamma`, `reward_scale` and `batch`, so the online agent and the offline learners see the same
//! rewards.
//!
//! The paper gives no settings for this agent; SPEC section 5 asks for what a practitioner would
//! use. The defaults are the usual DQN stabilisers: Double DQN, the Huber loss, gradient-norm
//! clipping at 10, a target network refreshed every 2 000 gradient steps, SPEC's [256, 256] network
//! and Adam at 1e-4. Without them the agent swings between heuristic level and far below random
//! from one evaluation to the next (docs/EXPERIMENTS.md).
//!
//! Loop, per environment step: epsilon-greedy action (uniform random during the first
//! `learning_starts` steps, then epsilon falls linearly from `eps_start` to `eps_end` over
//! `eps_decay_steps`), store the transition, and every `train_every` steps one Adam step on
//! eq. 7 over a uniform minibatch of the buffer. Time limits are not terminal: the last
//! transition of an episode is stored with `truncated = true` and still bootstraps.
//!
//! Snapshot selection (`dqn_select_every` > 0): once epsilon is at its floor, every
//! `dqn_select_every` steps and at the last step the greedy policy is evaluated exactly on the
//! agent's own task, and the best one is kept as the agent's policy. It only reads the network:
//! training, the replay buffer and the dataset are the same with or without it.

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use tch::Tensor;
use uavmeta_learner::batch::{Batch, BatchError};
use uavmeta_learner::dqn::{Bootstrap, TdConfig};
use uavmeta_learner::optim::{clip_grad_norm, FusedAdam};
use uavmeta_learner::qnet::{QNetwork, QNetworkConfig};
use uavmeta_learner::train::EvaluatePolicy;
use uavmeta_proto::config::{CollectConfig, Config, LearnerConfig, TaskConfig, WorldConfig};
use uavmeta_proto::dataset::Transition;

use crate::policy::q_policy::{Evaluator, QPolicy};
use crate::rollout::Policy;
use crate::world::World;

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

    /// The newest `n` transitions (all of them when `n` is 0 or above the length), oldest first.
    pub fn newest(&self, n: usize) -> impl Iterator<Item = &Transition> {
        let skip = match n {
            0 => 0,
            n => self.len().saturating_sub(n),
        };
        self.iter().skip(skip)
    }

    /// `n` transitions drawn uniformly with replacement.
    fn sample<'a>(&'a self, rng: &mut ChaCha8Rng, n: usize) -> Vec<&'a Transition> {
        (0..n)
            .map(|_| &self.items[rng.random_range(0..self.items.len())])
            .collect()
    }

    /// The slot of the transition stored after the one in slot `i`, if the buffer holds it.
    fn successor(&self, i: usize) -> Option<usize> {
        let j = (i + 1) % self.capacity;
        (j < self.items.len() && j != self.next && self.items[j].seq == self.items[i].seq + 1)
            .then_some(j)
    }

    /// The `n`-step transition from slot `i` and its bootstrap discount: the rewards of up to
    /// `n` consecutive transitions summed with discounts `gamma^k`, the last one's next state, and
    /// `gamma^m` for the `m <= n` transitions taken. The window stops at the episode's last
    /// transition (the horizon bootstraps from its next state) and at the newest stored one.
    fn n_step(&self, i: usize, n: usize, gamma: f64) -> (Transition, f64) {
        let first = &self.items[i];
        let (mut last, mut reward, mut discount) = (first, 0.0, 1.0);
        let mut slot = Some(i);
        for _ in 0..n {
            let Some(j) = slot else { break };
            last = &self.items[j];
            reward += discount * f64::from(last.reward);
            discount *= gamma;
            slot = if last.truncated {
                None
            } else {
                self.successor(j)
            };
        }
        let t = Transition {
            reward: reward as f32,
            next_obs: last.next_obs.clone(),
            truncated: last.truncated,
            ..first.clone()
        };
        (t, discount)
    }

    /// `batch` `n`-step transitions (see [`ReplayBuffer::n_step`]) from uniformly drawn slots,
    /// with their discounts.
    fn sample_n_step(
        &self,
        rng: &mut ChaCha8Rng,
        batch: usize,
        n: usize,
        gamma: f64,
    ) -> (Vec<Transition>, Vec<f32>) {
        (0..batch)
            .map(|_| {
                let (t, d) = self.n_step(rng.random_range(0..self.items.len()), n, gamma);
                (t, d as f32)
            })
            .unzip()
    }
}

/// Linear epsilon schedule from `eps_start` to `eps_end` over `eps_decay_steps`, counted from the
/// end of the uniform-random warm-up.
fn epsilon(c: &CollectConfig, step: usize) -> f64 {
    if step < c.learning_starts {
        return 1.0;
    }
    let progress = if c.eps_decay_steps == 0 {
        1.0
    } else {
        ((step - c.learning_starts) as f64 / c.eps_decay_steps as f64).min(1.0)
    };
    c.eps_start + (c.eps_end - c.eps_start) * progress
}

/// Episodes behind [`OnlineDqn::recent_return`]: one return is noise, the mean of 20 a trend.
pub const RECENT_EPISODES: usize = 20;

/// What one online DQN agent owns apart from its network and optimiser: its world, exploration
/// stream, replay buffer, episode returns and snapshot selection. [`OnlineDqn`] has one;
/// a population of agents trained as one computation
/// ([`crate::policy::dqn_population::DqnPopulation`]) has one per member, so the two share every
/// rule of the loop but the gradient step.
pub struct AgentState {
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
    /// The episodes snapshot selection scores a policy on.
    selector: Evaluator,
    /// The best snapshot so far (`collect.dqn_select_every` > 0); its step and return are
    /// [`AgentState::selected`].
    best: Option<QNetwork>,
    /// Every selection evaluation: (environment step, return).
    evaluations: Vec<(usize, f64)>,
}

impl AgentState {
    /// The state of the agent for task `task` (index `task_id`) acting as actor `actor`, and the
    /// seed of its network: all of them drawn from `seed`, in an order fixed once and for all.
    pub fn new(
        config: &Config,
        task: &TaskConfig,
        task_id: u32,
        actor: u32,
        seed: u64,
    ) -> (Self, u64) {
        let w = &config.world;
        let mut seeds = ChaCha8Rng::seed_from_u64(seed);
        let network_seed = seeds.random();
        let world = World::new(w, task, seeds.random());
        let rng = ChaCha8Rng::seed_from_u64(seeds.random());
        // Drawn last, so that the draws above are those of an agent without selection.
        let selector = Evaluator::new(w, task, config.learner.eval_episodes, seeds.random());
        let state = Self {
            world,
            replay: ReplayBuffer::new(config.collect.replay_capacity),
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
        };
        (state, network_seed)
    }

    /// ALGO: epsilon-greedy behaviour, the random half: `Some(uniform action)` with probability
    /// `epsilon`, `None` when the greedy action is due.
    pub fn explore(&mut self, epsilon: f64) -> Option<usize> {
        self.rng
            .random_bool(epsilon)
            .then(|| self.rng.random_range(0..self.world.action_count()))
    }

    /// The task index its transitions carry.
    pub fn task(&self) -> u32 {
        self.task
    }

    /// The actor number its transitions carry.
    pub fn actor(&self) -> u32 {
        self.actor
    }

    /// The world the agent acts in.
    pub fn world(&self) -> &World {
        &self.world
    }

    /// Takes `action`, stores the transition and, at the horizon, starts the next episode;
    /// returns the finished episode's return.
    pub fn advance(&mut self, action: usize) -> Option<f64> {
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

    /// A uniform minibatch of the replay buffer as tensors, with each row's bootstrap discount
    /// when `collect.dqn_n_step` > 1 (n-step windows, [`ReplayBuffer::n_step`]).
    pub fn sample(
        &mut self,
        collect: &CollectConfig,
        learner: &LearnerConfig,
        world: &WorldConfig,
    ) -> Result<(Batch, Option<Vec<f32>>), BatchError> {
        if collect.dqn_n_step == 1 {
            let sample = self.replay.sample(&mut self.rng, learner.batch);
            Ok((Batch::new(&sample, world, learner.reward_scale)?, None))
        } else {
            let (sample, discounts) = self.replay.sample_n_step(
                &mut self.rng,
                learner.batch,
                collect.dqn_n_step,
                learner.gamma,
            );
            let batch = Batch::new(&sample, world, learner.reward_scale)?;
            Ok((batch, Some(discounts)))
        }
    }

    /// Scores `q`'s greedy policy (the live network) and keeps it if it beats the best snapshot
    /// (the earlier one on a tie).
    pub fn select(&mut self, q: &QNetwork) {
        let ret = self.selector.evaluate(q).ret.mean;
        let better = self.selected().is_none_or(|(_, best)| ret > best);
        self.evaluations.push((self.steps, ret));
        match (&mut self.best, better) {
            (_, false) => {}
            (Some(best), true) => best.copy_from(q),
            (None, true) => self.best = Some(q.duplicate()),
        }
    }

    /// Logs the recent return every [`RECENT_EPISODES`] episodes, after an episode `finished`.
    pub fn log_progress(&self, finished: Option<f64>, epsilon: f64) {
        if finished.is_some() && self.returns.len().is_multiple_of(RECENT_EPISODES) {
            tracing::info!(
                task = self.task,
                actor = self.actor,
                steps = self.steps,
                episodes = self.returns.len(),
                epsilon,
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
        self.evaluations
            .iter()
            .copied()
            .reduce(|best, e| if e.1 > best.1 { e } else { best })
    }

    /// Every selection evaluation so far, (environment step, return), in order; the last one is
    /// the live network's at that step.
    pub fn selection_evaluations(&self) -> &[(usize, f64)] {
        &self.evaluations
    }

    /// The best snapshot, when selection has run.
    pub fn best(&self) -> Option<&QNetwork> {
        self.best.as_ref()
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
}

/// What every online DQN agent of a config reads: `[collect]`, `[learner]`, the world, and the TD
/// loss it trains on (eq. 7 with `[collect]`'s stabilisers).
pub struct DqnSettings {
    pub collect: CollectConfig,
    pub learner: LearnerConfig,
    pub world: WorldConfig,
    pub td: TdConfig,
}

impl DqnSettings {
    pub fn new(config: &Config) -> Self {
        Self {
            collect: config.collect.clone(),
            learner: config.learner.clone(),
            world: config.world.clone(),
            td: TdConfig {
                gamma: config.learner.gamma,
                bootstrap: Bootstrap::double_if(config.collect.dqn_double),
                huber: config.collect.dqn_huber,
            },
        }
    }
}

impl DqnSettings {
    // The rules of the loop that depend only on the step count, shared by `OnlineDqn` and the
    // population.

    /// The exploration rate of step `step`.
    pub fn epsilon(&self, step: usize) -> f64 {
        epsilon(&self.collect, step)
    }

    /// The learning rate of the gradient step after `step` environment steps: `dqn_lr`, falling
    /// linearly to `dqn_lr * dqn_lr_final_fraction` between `learning_starts` and `dqn_steps`.
    pub fn learning_rate(&self, step: usize) -> f64 {
        let c = &self.collect;
        let span = c.dqn_steps.saturating_sub(c.learning_starts).max(1);
        let progress = (step.saturating_sub(c.learning_starts) as f64 / span as f64).min(1.0);
        c.dqn_lr * (1.0 - (1.0 - c.dqn_lr_final_fraction) * progress)
    }

    /// Whether a gradient step is due once `steps` environment steps are taken.
    pub fn train_due(&self, steps: usize) -> bool {
        steps >= self.collect.learning_starts && steps.is_multiple_of(self.collect.train_every)
    }

    /// Whether a selection evaluation is due once `steps` environment steps are taken: every
    /// `dqn_select_every` steps once epsilon is at its floor, and the last of `dqn_steps`.
    pub fn selection_due(&self, steps: usize) -> bool {
        let c = &self.collect;
        c.dqn_select_every > 0
            && (steps == c.dqn_steps
                || (steps >= c.learning_starts + c.eps_decay_steps
                    && steps.is_multiple_of(c.dqn_select_every)))
    }

    /// Whether the target network is refreshed after `gradient_steps` gradient steps.
    pub fn target_due(&self, gradient_steps: usize) -> bool {
        gradient_steps.is_multiple_of(self.collect.dqn_target_update_every)
    }
}

/// One online DQN agent training in one task's world.
pub struct OnlineDqn {
    settings: DqnSettings,
    state: AgentState,
    q: QNetwork,
    target: QNetwork,
    opt: FusedAdam,
    gradient_steps: usize,
}

impl OnlineDqn {
    /// An untrained agent for task `task` (index `task_id` in the config's `[[tasks]]`), acting as
    /// actor `actor`. Its network, world and exploration all derive from `seed`.
    pub fn new(config: &Config, task: &TaskConfig, task_id: u32, actor: u32, seed: u64) -> Self {
        let c = &config.collect;
        let (state, network_seed) = AgentState::new(config, task, task_id, actor, seed);
        let q = QNetworkConfig::for_world(&config.world, &c.dqn_hidden).init(network_seed);
        let target = q.duplicate();
        let opt = FusedAdam::new(q.parameters(), c.dqn_lr);
        Self {
            settings: DqnSettings::new(config),
            state,
            q,
            target,
            opt,
            gradient_steps: 0,
        }
    }

    /// Trains for `collect.dqn_steps` environment steps.
    pub fn train(&mut self) -> Result<(), BatchError> {
        self.train_steps(self.settings.collect.dqn_steps)
    }

    /// Trains for `steps` more environment steps, logging the recent return every
    /// [`RECENT_EPISODES`] episodes.
    pub fn train_steps(&mut self, steps: usize) -> Result<(), BatchError> {
        for _ in 0..steps {
            let finished = self.step()?;
            self.state.log_progress(finished, self.epsilon());
        }
        Ok(())
    }

    /// The learning rate of the next gradient step (see [`DqnSettings::learning_rate`]).
    pub fn learning_rate(&self) -> f64 {
        self.settings.learning_rate(self.state.steps)
    }

    /// The exploration rate of the next step.
    pub fn epsilon(&self) -> f64 {
        self.settings.epsilon(self.state.steps)
    }

    /// Mean return of the last [`RECENT_EPISODES`] finished episodes; `None` before the first.
    pub fn recent_return(&self) -> Option<f64> {
        self.state.recent_return()
    }

    /// One environment step (and the gradient step it is due); the episode's return when the step
    /// ended an episode.
    pub fn step(&mut self) -> Result<Option<f64>, BatchError> {
        // ALGO: epsilon-greedy behaviour.
        let action = match self.state.explore(self.epsilon()) {
            Some(random) => random,
            None => QPolicy::new(&self.q).act(self.state.world()),
        };
        let finished = self.state.advance(action);
        if self.settings.train_due(self.state.steps) {
            self.gradient_step()?;
        }
        if self.settings.selection_due(self.state.steps) {
            self.state.select(&self.q);
        }
        Ok(finished)
    }

    /// ALGO: one Adam step on eq. 7 (with the configured stabilisers) over a uniform minibatch of
    /// the replay buffer.
    fn gradient_step(&mut self) -> Result<(), BatchError> {
        self.opt.set_lr(self.learning_rate());
        let (mb, discounts) = self.state.sample(
            &self.settings.collect,
            &self.settings.learner,
            &self.settings.world,
        )?;
        let q_all = self.q.forward(&mb.obs); // [B, A]
        let target = |s: &Tensor| self.target.forward(s);
        let online = |s: &Tensor| self.q.forward(s);
        let loss = match discounts {
            None => self.settings.td.td_errors(&q_all, &mb, target, online),
            Some(d) => {
                let d = Tensor::from_slice(&d);
                self.settings
                    .td
                    .td_errors_discounted(&q_all, &mb, &d, target, online)
            }
        }
        .mean(None); // eq. 7 (n-step when dqn_n_step > 1) and its stabilisers
        self.opt.zero_grad();
        loss.backward();
        let clip = self.settings.collect.dqn_grad_clip_norm;
        if clip > 0.0 {
            clip_grad_norm(&self.q.parameters(), clip);
        }
        self.opt.step();
        self.gradient_steps += 1;
        if self.settings.target_due(self.gradient_steps) {
            self.target.copy_from(&self.q);
        }
        Ok(())
    }

    /// The step and evaluated return of the snapshot selection has kept so far, if any.
    pub fn selected(&self) -> Option<(usize, f64)> {
        self.state.selected()
    }

    /// Every selection evaluation so far, (environment step, return), in order.
    pub fn selection_evaluations(&self) -> &[(usize, f64)] {
        self.state.selection_evaluations()
    }

    /// The replay buffer, from which the paper's offline dataset of this task is sampled.
    pub fn replay_buffer(&self) -> &ReplayBuffer {
        self.state.replay_buffer()
    }

    /// The agent's Q-network, whose greedy policy ([`QPolicy`]) is the "online DQN" reference:
    /// the best snapshot when selection is on and has run, else the network being trained.
    pub fn q_network(&self) -> &QNetwork {
        self.state.best().unwrap_or(&self.q)
    }

    /// Returns of the finished training episodes, in order.
    pub fn episode_returns(&self) -> &[f64] {
        self.state.episode_returns()
    }

    /// Environment steps taken so far.
    pub fn steps(&self) -> usize {
        self.state.steps
    }

    /// Its per-agent state: world, replay buffer, returns, selection.
    pub fn state(&self) -> &AgentState {
        &self.state
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A transition of episode `episode`, step `step`, seq `seq`, reward `reward`, whose next
    /// observation's first value is `seq + 1` (so a window's end can be read off).
    fn transition(seq: u64, episode: u64, step: u32, reward: f32, truncated: bool) -> Transition {
        Transition {
            task: 0,
            actor: 0,
            episode,
            step,
            seq,
            obs: vec![seq as u16],
            action: 0,
            reward,
            next_obs: vec![seq as u16 + 1],
            truncated,
        }
    }

    /// Episodes of 3 steps, rewards -1, -2, -3, ... in seq order.
    fn buffer(capacity: usize, pushed: u64) -> ReplayBuffer {
        let mut b = ReplayBuffer::new(capacity);
        for seq in 0..pushed {
            let step = (seq % 3) as u32;
            b.push(transition(
                seq,
                seq / 3,
                step,
                -(seq as f32 + 1.0),
                step == 2,
            ));
        }
        b
    }

    fn slot_of(b: &ReplayBuffer, seq: u64) -> usize {
        b.items.iter().position(|t| t.seq == seq).unwrap()
    }

    #[test]
    fn n_step_windows_sum_discounted_rewards_and_stop_at_the_episode_and_the_buffer_end() {
        let gamma = 0.5;
        let b = buffer(100, 8);
        // Within an episode: seq 0, 1, 2 with n = 3 (seq 2 ends the episode).
        let (t, d) = b.n_step(slot_of(&b, 0), 3, gamma);
        assert_eq!(
            (t.reward, d, t.next_obs[0], t.obs[0]),
            (-1.0 - 1.0 - 0.75, 0.125, 3, 0)
        );
        // Cut at the episode's end: from seq 1, n = 3 takes seq 1 and 2 only.
        let (t, d) = b.n_step(slot_of(&b, 1), 3, gamma);
        assert_eq!((t.reward, d, t.next_obs[0]), (-2.0 - 1.5, 0.25, 3));
        assert!(t.truncated);
        // Cut at the newest transition: seq 7 has no successor.
        let (t, d) = b.n_step(slot_of(&b, 7), 3, gamma);
        assert_eq!((t.reward, d, t.next_obs[0]), (-8.0, 0.5, 8));
        // n = 1 is the transition itself.
        let (t, d) = b.n_step(slot_of(&b, 4), 1, gamma);
        assert_eq!((t.reward, d, t.next_obs[0]), (-5.0, 0.5, 5));
    }

    #[test]
    fn n_step_windows_follow_the_ring_and_never_wrap_from_the_newest_to_the_oldest() {
        let gamma = 0.5;
        // Capacity 4 after 7 pushes holds seq 3, 4, 5, 6; slots [4, 5, 6, 3], the oldest at 3.
        let b = buffer(4, 7);
        assert_eq!(b.iter().map(|t| t.seq).collect::<Vec<_>>(), [3, 4, 5, 6]);
        // seq 3 -> 4 -> 5 (the episode's end) crosses the ring's seam at slot 3 -> 0.
        let (t, d) = b.n_step(slot_of(&b, 3), 3, gamma);
        assert_eq!((t.reward, d, t.next_obs[0]), (-4.0 - 2.5 - 1.5, 0.125, 6));
        // seq 6 is the newest: its successor slot holds seq 3, which is not seq 7.
        let (t, d) = b.n_step(slot_of(&b, 6), 3, gamma);
        assert_eq!((t.reward, d, t.next_obs[0]), (-7.0, 0.5, 7));
    }
}
