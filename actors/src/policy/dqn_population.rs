//! A population of online DQN agents trained in lockstep as one computation (issue #33).
//!
//! Member i is the agent [`OnlineDqn`](crate::policy::dqn_online::OnlineDqn) would train for its own task and seed: the same world,
//! exploration stream, replay buffer, schedules and snapshot selection ([`AgentState`], shared
//! with the single agent), the same initial network. What the members share is the arithmetic:
//! their networks are one [`QPopulation`], so every step's greedy actions are one forward pass
//! over `[N, 1, D]` and every gradient step one batched forward, backward and Adam step over
//! `[N, B, ..]`. Their losses are summed, each member's its own mean (eq. 7), so no gradient
//! crosses between members; clipping takes each member's own norm.
//!
//! A population of one is bit for bit the single agent; of N, each member follows its separate
//! run up to float rounding (`actors/tests/population.rs`).

use tch::{Device, Tensor};
use uavmeta_learner::batch::{Batch, BatchError};
use uavmeta_learner::optim::FusedAdam;
use uavmeta_learner::population::QPopulation;
use uavmeta_learner::qnet::{QNetwork, QNetworkConfig};
use uavmeta_proto::config::{Config, TaskConfig};

use crate::policy::dqn_online::{AgentState, DqnSettings};

/// Who a member is: the task it trains on (and its index in the config's `[[tasks]]`), the actor
/// number its transitions carry, and its seed.
#[derive(Debug, Clone)]
pub struct MemberSpec {
    pub task: TaskConfig,
    pub task_id: u32,
    pub actor: u32,
    pub seed: u64,
}

/// N online DQN agents of one configuration, stepped and trained together.
pub struct DqnPopulation {
    settings: DqnSettings,
    members: Vec<AgentState>,
    q: QPopulation,
    target: QPopulation,
    opt: FusedAdam,
    gradient_steps: usize,
    /// Each member's normalised observation, reused every step: [N * D].
    obs: Vec<f32>,
}

impl DqnPopulation {
    /// One untrained agent per spec, all under `config` (whose `[[tasks]]` the specs' tasks need
    /// not be), with their networks on `device`.
    ///
    /// # Panics
    /// If `members` is empty.
    pub fn new(config: &Config, members: &[MemberSpec], device: Device) -> Self {
        let c = &config.collect;
        let (states, seeds): (Vec<AgentState>, Vec<u64>) = members
            .iter()
            .map(|m| AgentState::new(config, &m.task, m.task_id, m.actor, m.seed))
            .unzip();
        let shape = QNetworkConfig::for_world(&config.world, &c.dqn_hidden);
        let q = QPopulation::init(&shape, &seeds, device);
        let target = q.duplicate();
        let opt = FusedAdam::new(q.parameters(), c.dqn_lr);
        Self {
            settings: DqnSettings::new(config),
            obs: vec![0.0; members.len() * shape.obs_len],
            members: states,
            q,
            target,
            opt,
            gradient_steps: 0,
        }
    }

    /// Trains every member for `steps` more environment steps.
    pub fn train_steps(&mut self, steps: usize) -> Result<(), BatchError> {
        for _ in 0..steps {
            self.step()?;
        }
        Ok(())
    }

    /// One environment step of every member, then the gradient step and the selection
    /// evaluations it is due.
    pub fn step(&mut self) -> Result<(), BatchError> {
        let epsilon = self.settings.epsilon(self.steps());
        // ALGO: epsilon-greedy behaviour, each member with its own stream.
        let explored: Vec<Option<usize>> = self
            .members
            .iter_mut()
            .map(|m| m.explore(epsilon))
            .collect();
        let greedy = if explored.iter().any(Option::is_none) {
            self.greedy_actions()
        } else {
            Vec::new()
        };
        let next_epsilon = self.settings.epsilon(self.steps() + 1);
        for (i, (m, random)) in self.members.iter_mut().zip(explored).enumerate() {
            let finished = m.advance(random.unwrap_or_else(|| greedy[i]));
            m.log_progress(finished, next_epsilon);
        }
        if self.settings.train_due(self.steps()) {
            self.gradient_step()?;
        }
        if self.settings.selection_due(self.steps()) {
            for (i, m) in self.members.iter_mut().enumerate() {
                m.select(&self.q.member(i));
            }
        }
        Ok(())
    }

    /// Each member's greedy action in its own world: one forward pass over [N, 1, D].
    fn greedy_actions(&mut self) -> Vec<usize> {
        let d = self.q.config().obs_len;
        for (m, obs) in self.members.iter().zip(self.obs.chunks_exact_mut(d)) {
            m.world().write_normalised(obs);
        }
        let n = self.members.len() as i64;
        let obs = Tensor::from_slice(&self.obs)
            .view([n, 1, d as i64])
            .to_device(self.q.device());
        let actions = self.q.greedy(&obs).view([n]).to_device(Device::Cpu);
        Vec::<i64>::try_from(actions)
            .expect("greedy actions are an i64 vector")
            .into_iter()
            .map(|a| a as usize)
            .collect()
    }

    /// ALGO: one Adam step on the sum over members of each member's eq. 7 (with the configured
    /// stabilisers), each over a uniform minibatch of its own replay buffer.
    fn gradient_step(&mut self) -> Result<(), BatchError> {
        self.opt.set_lr(self.settings.learning_rate(self.steps()));
        let mut batches = Vec::with_capacity(self.members.len());
        let mut discounts = Vec::new();
        for m in &mut self.members {
            let (batch, d) = m.sample(
                &self.settings.collect,
                &self.settings.learner,
                &self.settings.world,
            )?;
            batches.push(batch);
            discounts.extend(d.unwrap_or_default());
        }
        let device = self.q.device();
        let mb = Batch::stack(&batches, device); // [N, B, ..]
        let q_all = self.q.forward(&mb.obs); // [N, B, A]
        let target = |s: &Tensor| self.target.forward(s);
        let online = |s: &Tensor| self.q.forward(s);
        let errors = if discounts.is_empty() {
            self.settings.td.td_errors(&q_all, &mb, target, online)
        } else {
            let d = Tensor::from_slice(&discounts)
                .view([batches.len() as i64, -1])
                .to_device(device);
            self.settings
                .td
                .td_errors_discounted(&q_all, &mb, &d, target, online)
        }; // [N, B]
           // Each member's eq. 7 (its mean over its batch), summed: member i's weights get
           // exactly the gradient of its own loss.
        let loss = errors.mean_dim([-1].as_slice(), false, None).sum(None);
        self.opt.zero_grad();
        loss.backward();
        let clip = self.settings.collect.dqn_grad_clip_norm;
        if clip > 0.0 {
            self.q.clip_grad_norm(clip);
        }
        self.opt.step();
        self.gradient_steps += 1;
        if self.settings.target_due(self.gradient_steps) {
            self.target.copy_from(&self.q);
        }
        Ok(())
    }

    /// Member `i`'s state: world, replay buffer, returns, selection.
    pub fn member(&self, i: usize) -> &AgentState {
        &self.members[i]
    }

    /// Every member's state, in spec order.
    pub fn members(&self) -> &[AgentState] {
        &self.members
    }

    /// Member `i`'s policy network, as [`OnlineDqn::q_network`](crate::policy::dqn_online::OnlineDqn::q_network): the best snapshot when
    /// selection is on and has run, else the network being trained (a copy).
    pub fn q_network(&self, i: usize) -> QNetwork {
        match self.members[i].best() {
            Some(best) => best.duplicate(),
            None => self.q.member(i),
        }
    }

    /// The live networks of every member.
    pub fn networks(&self) -> &QPopulation {
        &self.q
    }

    /// Environment steps each member has taken (they step in lockstep).
    pub fn steps(&self) -> usize {
        self.members[0].steps()
    }
}
