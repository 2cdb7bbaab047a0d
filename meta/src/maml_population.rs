//! Meta-training of a population (issue #33): N meta-learners of one shape (one [`MamlConfig`],
//! one architecture, the same number of meta-train tasks with support sets of the same size)
//! running Algorithm 4 in lockstep, for the several seeds of one init in `uavmeta reproduce`.
//!
//! Member m is the meta-learner [`Maml`] would make of its own `w0` and seed: its own sampling
//! stream (support passes, tasks, shots, in the same order), its own target network, Meta-SGD
//! step sizes, Polyak average and Adam moments. What the members share is the arithmetic: an
//! outer step adapts all N x T (member, task) pairs in one stacked computation
//! ([`MamlConfig::backward_meta_loss_population`]) and updates every member's `w0` with one fused
//! Adam step, which, being elementwise, keeps each member's moments apart. The meta-loss is the
//! sum over members of each member's own, so member m's `w0` gets exactly its own meta-gradient.
//!
//! A population of one is [`Maml`] bit for bit; of N, each member follows its separate
//! meta-training up to float rounding (`meta/tests/maml_population.rs`). To evaluate or
//! checkpoint a member, [`MamlPopulation::member`] unstacks it into the [`Maml`] it stands for.

use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use tch::{Device, Tensor};
use uavmeta_learner::optim::FusedAdam;
use uavmeta_learner::population::QPopulation;
use uavmeta_learner::progress::OnStep;
use uavmeta_learner::qnet::QNetwork;

use crate::maml::{
    meta_parameters, outer_optimizer, EpochDraws, Maml, MamlConfig, MetaEpoch, MetaTask, StepSize,
};
use crate::MetaError;

/// N meta-learners' `w0`, step sizes, target networks and outer Adam, stacked.
pub struct MamlPopulation {
    config: MamlConfig,
    /// The iterates eq. 16 updates, [N, ..].
    w0: QPopulation,
    /// The moving averages of the iterates, when `w0_average_decay` > 0.
    average: Option<QPopulation>,
    /// Meta-SGD's per-weight step sizes, [N, ..] leaves, when `learn_inner_lr`.
    inner_lr: Option<Vec<Tensor>>,
    target: QPopulation,
    optimizer: FusedAdam,
    /// Member m's sampling stream.
    rngs: Vec<ChaCha8Rng>,
    epochs_done: usize,
    /// Called at every lockstep outer step.
    on_step: OnStep,
}

impl MamlPopulation {
    /// Member m meta-trains `w0s[m]` drawing from `seeds[m]`, as `Maml::new(w0s[m], config,
    /// seeds[m])` does; the stacked tensors live on `device`.
    ///
    /// # Panics
    /// If `w0s` is empty, its networks differ in architecture, or `seeds` is not one per network:
    /// the caller groups members by shape.
    pub fn new(w0s: &[QNetwork], config: MamlConfig, seeds: &[u64], device: Device) -> Self {
        assert_eq!(w0s.len(), seeds.len(), "one seed per member");
        let w0 = QPopulation::from_networks(w0s, device);
        let (inner_lr, optimizer) = outer_optimizer(w0.parameters(), &config);
        let target = w0.duplicate();
        let average = (config.meta.w0_average_decay > 0.0).then(|| w0.duplicate());
        Self {
            config,
            w0,
            average,
            inner_lr,
            target,
            optimizer,
            rngs: seeds
                .iter()
                .map(|&s| ChaCha8Rng::seed_from_u64(s))
                .collect(),
            epochs_done: 0,
            on_step: OnStep::default(),
        }
    }

    /// The population with `on_step` called at every lockstep outer step.
    pub fn with_on_step(self, on_step: OnStep) -> Self {
        Self { on_step, ..self }
    }

    /// N.
    pub fn members(&self) -> usize {
        self.rngs.len()
    }

    /// One meta-epoch of Algorithm 4 for every member, member m over `tasks[m]`; each member's
    /// figures, as [`Maml::meta_epoch`] gives them.
    pub fn meta_epoch(&mut self, tasks: &[&[MetaTask]]) -> Result<Vec<MetaEpoch>, MetaError> {
        let steps = self.check_shape(tasks)?;
        if (self.epochs_done).is_multiple_of(self.config.meta.target_update_every) {
            self.target.copy_from(&self.w0); // Qhat <- w0, constant until the next refresh
        }
        self.optimizer
            .set_lr(self.config.eta_outer_at(self.epochs_done));
        let mut draws: Vec<EpochDraws> = (tasks.iter().zip(&mut self.rngs))
            .map(|(tasks, rng)| EpochDraws::new(tasks, rng))
            .collect();
        for _ in 0..steps {
            self.on_step.step();
            let (picked, shots): (Vec<_>, Vec<_>) = (draws.iter_mut().zip(tasks))
                .zip(&mut self.rngs)
                .map(|((draws, tasks), rng)| draws.next(&self.config.meta, tasks, rng))
                .unzip();
            // Eqs. 14-15 for every (member, task) pair, each member's meta-gradient into its own
            // slice of the stacked w0 (and step sizes).
            self.optimizer.zero_grad();
            let step = match &self.inner_lr {
                Some(lr) => StepSize::PerWeight(lr),
                None => StepSize::Shared,
            };
            let losses = self.config.backward_meta_loss_population(
                &self.w0.parameters(),
                step,
                &self.target.parameters(),
                &shots,
            );
            // Eq. 16: one Adam(eta_outer) step over every member's w0 (and step sizes).
            self.optimizer.step();
            if let Some(average) = &mut self.average {
                average.average_toward(&self.w0, self.config.meta.w0_average_decay);
            }
            for ((draws, picked), losses) in draws.iter_mut().zip(picked).zip(losses) {
                draws.record(picked, losses);
            }
        }
        self.epochs_done += 1;
        Ok((draws.into_iter())
            .map(|d| d.finish(self.epochs_done))
            .collect())
    }

    /// The outer steps of a meta-epoch, the same for every member, or which member differs: one
    /// task set per member, each as many tasks with as many outer steps as member 0's.
    fn check_shape(&self, tasks: &[&[MetaTask]]) -> Result<usize, MetaError> {
        let shape = |tasks: &[MetaTask]| (tasks.len(), self.config.outer_steps(tasks));
        let expected = shape(tasks.first().copied().unwrap_or_default());
        if tasks.len() != self.members() {
            return Err(MetaError::PopulationShape {
                member: tasks.len().min(self.members()),
                got: format!("task sets for {} members", tasks.len()),
                expected: format!("one task set per member ({})", self.members()),
            });
        }
        if expected.0 == 0 {
            return Err(MetaError::NoTasks);
        }
        for (member, tasks) in tasks.iter().enumerate() {
            let (count, steps) = shape(tasks);
            if (count, steps) != expected {
                return Err(MetaError::PopulationShape {
                    member,
                    got: format!("{count} tasks, {steps} outer steps per meta-epoch"),
                    expected: format!(
                        "{} tasks, {} outer steps per meta-epoch (member 0's)",
                        expected.0, expected.1
                    ),
                });
            }
        }
        Ok(expected.1)
    }

    /// Member `m` unstacked: the single meta-learner it stands for (its `w0`, average, step
    /// sizes, target, Adam moments and sampling stream, copied to the CPU), to evaluate, adapt
    /// or checkpoint with [`Maml`]'s own methods.
    ///
    /// # Panics
    /// If `m` is not below [`members`](Self::members).
    pub fn member(&self, m: usize) -> Maml {
        let w0 = self.w0.member(m);
        let inner_lr: Option<Vec<Tensor>> = self.inner_lr.as_ref().map(|lr| {
            lr.iter()
                .map(|p| {
                    (p.get(m as i64).detach())
                        .to_device(Device::Cpu)
                        .copy()
                        .set_requires_grad(true)
                })
                .collect()
        });
        let mut optimizer = FusedAdam::new(
            meta_parameters(w0.parameters(), &inner_lr),
            self.config.eta_outer_at(self.epochs_done),
        );
        let moments = (self.optimizer.moments())
            .map(|(mean, square)| (mean.get(m as i64), square.get(m as i64)))
            .collect();
        optimizer.restore(moments, self.optimizer.steps());
        Maml {
            config: self.config.clone(),
            w0,
            average: self.average.as_ref().map(|a| a.member(m)),
            inner_lr,
            target: self.target.member(m),
            optimizer,
            rng: self.rngs[m].clone(),
            epochs_done: self.epochs_done,
            on_step: OnStep::default(),
        }
    }
}
