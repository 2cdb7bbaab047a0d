//! The task-inferring learner: context-based offline meta-RL after FOCAL (Li, Yang and Luo,
//! ICLR 2021, "FOCAL: efficient fully-offline meta-reinforcement learning via distance metric
//! learning and behavior regularization"), docs/MODEL.md section 5. A task encoder reads a set of
//! a task's transitions and writes a task code; a Q-network reads the observation and the code.
//! At meta-test the unseen task's shots are encoded and the policy acts at once, with no gradient
//! step:
//!
//! ```text
//! e_phi(s, a, r, s')  an MLP over one transition (a one-hot, r scaled)           [d]
//! z = E_phi(c)        = mean over the transitions of a context c of e_phi         the task code
//! L_enc(phi, V)       = mean over contexts c of || V z(c) - p(tau_c) ||^2         p: the task's
//!                       parameters (lambda / max |lambda|, rain, the rain zone's corners)
//! L(w)                = eq. 8 on ([s, z], a, r, [s', z]), z = E_phi(c) of a context of the
//!                       transition's own task, phi held fixed
//! pi(s)               = argmax_a Q_w([s, z*], a),  z* = E_phi(every shot of the unseen task)
//! ```
//!
//! The encoder learns to read the task's known parameters through a linear head V. FOCAL's own
//! distance-metric loss, which only pushes different tasks' codes apart, gave codes that place an
//! unseen lambda less well: its zero-shot policy on lambda-300 scored 0.9% lower
//! (docs/EXPERIMENTS.md, F2). As in FOCAL, the Q-network learns from its own loss with the codes
//! as fixed inputs; so the encoder trains first (`context.encoder_steps` Adam steps, each on two
//! contexts of `context.transitions_per_context` transitions per meta-train task), then the Q-network. The
//! Q-network trains exactly as CQL-pretrain's does ([`crate::pretrain::train_multi_task`]: the
//! same algorithm, budget and minibatches on the union of the meta-train tasks' shots), each
//! transition carrying the code of one of [`CODES_PER_TASK`] contexts of its task: the two inits
//! differ only in what the code tells the network.
//!
//! With z* fixed, `Q_w(., z*)` is an MLP on s alone whose first layer's bias has absorbed
//! `W_z z*` ([`ContextModel::policy`]): the zero-shot policy is a plain Q-network, evaluated and
//! checkpointed like any other, and `cql-context` fine-tunes it on the shots as `cql-maml`
//! fine-tunes w0.

use std::path::{Path, PathBuf};

use rand::seq::index;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};
use tch::{Kind, Tensor};
use uavmeta_actors::policy::q_policy::Evaluator;
use uavmeta_learner::checkpoint::{self, CheckpointError};
use uavmeta_learner::optim::FusedAdam;
use uavmeta_learner::progress::{progress_bar, OnStep};
use uavmeta_learner::qnet::{QNetwork, QNetworkConfig};
use uavmeta_learner::train::EvaluatePolicy;
use uavmeta_learner::transitions::Transitions;
use uavmeta_proto::config::{Config, TaskConfig, WorldConfig};
use uavmeta_proto::method::{Method, Start};

use crate::maml::MetaTask;
use crate::meta_train::{load_tasks, MetaTrainOptions};
use crate::pretrain::train_multi_task;
use crate::{create_dir, write_file, MetaError};

/// Contexts per meta-train task whose codes the Q-network's training rows carry, one each.
pub const CODES_PER_TASK: usize = 16;

/// The encoder and the task-conditioned Q-network.
pub struct ContextModel {
    /// `e_phi`: (s, onehot a, r, s') -> [d] (an MLP; its "actions" are the code's values).
    pub encoder: QNetwork,
    /// `Q_w([s, z], .)`.
    pub q: QNetwork,
}

/// What a saved model's encoder is, beside its Q-network's checkpoint.
#[derive(Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct EncoderMeta {
    latent: usize,
    hidden: Vec<usize>,
}

impl ContextModel {
    /// The task code d.
    pub fn latent(&self) -> usize {
        self.encoder.actions()
    }

    /// The code of each context: `contexts` [M, C, input] rows of [`encoder_input`] ->
    /// [M, d], or [C, input] -> [d].
    pub fn encode(&self, contexts: &Tensor) -> Tensor {
        encode(&self.encoder, contexts)
    }

    /// The zero-shot policy for the task whose shots are `shots`: `Q_w(., z*)`, z* the code of
    /// every shot, as a Q-network on the observation alone.
    pub fn policy(&self, shots: &Transitions) -> QNetwork {
        let code = tch::no_grad(|| self.encode(&encoder_input(shots, self.q.actions())));
        self.q.conditioned_on(&code)
    }

    /// Saves the model as checkpoint `path` (the Q-network, named by the method fine-tuned from
    /// it) with the encoder beside it (`path.state.*`).
    pub fn save(&self, path: &Path, config: &Config) -> Result<(), CheckpointError> {
        let tensors: Vec<(String, Tensor)> = self.encoder.vs.variables().into_iter().collect();
        let meta = EncoderMeta {
            latent: self.latent(),
            hidden: self.encoder.hidden().to_vec(),
        };
        checkpoint::save_state(path, &tensors, &meta)?;
        let name = Method::tuned(config.meta.inner_loss, Start::Context).name();
        checkpoint::save(path, &self.q, &name, config.meta.meta_epochs, config)?;
        Ok(())
    }

    /// Loads a model [`ContextModel::save`] wrote, sized by its own metadata and checked
    /// against `config`'s world and `learner.hidden`.
    pub fn load(path: &Path, config: &Config) -> Result<ContextModel, CheckpointError> {
        let (tensors, meta) = checkpoint::load_state::<EncoderMeta>(path)?;
        let (q, _) = checkpoint::load_conditioned(path, config, meta.latent)?;
        let world = &config.world;
        let input = encoder_input_len(
            world.layout().observation_len(),
            world.layout().action_count(),
        );
        let encoder = QNetworkConfig::new(input, meta.latent, &meta.hidden).init(0);
        let mut variables = encoder.vs.variables();
        let state = checkpoint::state_paths(path).0;
        let mismatch = |detail: String| CheckpointError::SizeMismatch {
            path: state.clone(),
            key: "context",
            detail,
        };
        if tensors.len() != variables.len() {
            return Err(mismatch(format!(
                "{} tensors, expected the encoder's {}",
                tensors.len(),
                variables.len()
            )));
        }
        for (name, value) in tensors {
            let Some(variable) = variables.get_mut(&name) else {
                return Err(mismatch(format!("`{name}` is not an encoder tensor")));
            };
            if variable.size() != value.size() {
                return Err(mismatch(format!(
                    "`{name}` is {:?}, expected {:?}",
                    value.size(),
                    variable.size()
                )));
            }
            tch::no_grad(|| variable.copy_(&value));
        }
        Ok(ContextModel { encoder, q })
    }
}

/// `encoder`'s code of each context, the mean of its transitions' codes: [M, C, input] ->
/// [M, d], or [C, input] -> [d].
fn encode(encoder: &QNetwork, contexts: &Tensor) -> Tensor {
    encoder
        .forward(contexts)
        .mean_dim([-2i64].as_slice(), false, None)
}

/// Values the encoder reads per transition: s, onehot(a), r, s'.
pub fn encoder_input_len(obs_len: usize, actions: usize) -> usize {
    2 * obs_len + actions + 1
}

/// The encoder's input rows of `batch`: [B, 2D + A + 1].
pub fn encoder_input(batch: &Transitions, actions: usize) -> Tensor {
    let onehot = batch.actions.one_hot(actions as i64).to_kind(Kind::Float);
    Tensor::cat(
        &[
            batch.obs.shallow_clone(),
            onehot,
            batch.rewards.unsqueeze(-1),
            batch.next_obs.shallow_clone(),
        ],
        -1,
    )
}

/// What the encoder's head learns to read from a context of each task: lambda over the largest
/// |lambda| of `tasks`, then 1 where it rains and the rain zone's corners over the grid's last
/// cell (0 without rain): [T, 6].
pub fn task_parameters(tasks: &[&TaskConfig], world: &WorldConfig) -> Tensor {
    let scale = (tasks.iter().map(|t| t.lambda.abs()).fold(0.0, f64::max)).max(f64::MIN_POSITIVE);
    let span = f64::from(world.grid_cells.max(2) - 1);
    let rows: Vec<f32> = tasks
        .iter()
        .flat_map(|t| {
            let rain = t.rain.map_or([0.0; 5], |z| {
                let corner = |c: u32| f64::from(c) / span;
                [1.0, corner(z.x0), corner(z.y0), corner(z.x1), corner(z.y1)]
            });
            std::iter::once(t.lambda / scale)
                .chain(rain)
                .map(|v| v as f32)
        })
        .collect();
    Tensor::from_slice(&rows).view([tasks.len() as i64, 6])
}

/// `count` contexts of `transitions_per_context` rows of `data` each, drawn without replacement within a
/// context: [count, C, input].
fn contexts(
    data: &Transitions,
    transitions_per_context: usize,
    count: usize,
    actions: usize,
    rng: &mut ChaCha8Rng,
) -> Tensor {
    let c = transitions_per_context.min(data.len());
    let rows: Vec<i64> = (0..count)
        .flat_map(|_| {
            index::sample(rng, data.len(), c)
                .into_iter()
                .map(|i| i as i64)
        })
        .collect();
    let picked = data.select(&Tensor::from_slice(&rows));
    encoder_input(&picked, actions).view([count as i64, c as i64, -1])
}

/// The encoder trained to read `parameters` [T, P] (one row per task of `data`) from contexts of
/// each task's data, through a linear head, from the inits of `seed`: each step draws two
/// contexts per task.
pub fn train_encoder(
    config: &Config,
    data: &[Transitions],
    parameters: &Tensor,
    seed: u64,
) -> QNetwork {
    let ctx = &config.context;
    let (obs_len, actions) = (
        config.world.layout().observation_len(),
        config.world.layout().action_count(),
    );
    let input = encoder_input_len(obs_len, actions);
    let encoder = QNetworkConfig::new(input, ctx.latent, &ctx.encoder_hidden).init(seed);
    let head = QNetworkConfig::new(ctx.latent, parameters.size()[1] as usize, &[])
        .init(seed.wrapping_add(1));
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut params = encoder.parameters();
    params.extend(head.parameters());
    let mut opt = FusedAdam::new(params, config.learner.lr);
    let tasks: Vec<i64> = (0..data.len() as i64).flat_map(|t| [t, t]).collect();
    let targets = parameters.index_select(0, &Tensor::from_slice(&tasks));
    for _ in 0..ctx.encoder_steps {
        let codes: Vec<Tensor> = data
            .iter()
            .map(|d| {
                encode(
                    &encoder,
                    &contexts(d, ctx.transitions_per_context, 2, actions, &mut rng),
                )
            })
            .collect();
        let read = head.forward(&Tensor::cat(&codes, 0));
        opt.backward_step(&(read - &targets).square().mean(None));
    }
    encoder
}

/// `data` with a task code after each observation (the same after s and s'): the codes of
/// [`CODES_PER_TASK`] contexts of `data`, one drawn for each row.
fn with_codes(
    model_encoder: &QNetwork,
    data: &Transitions,
    config: &Config,
    rng: &mut ChaCha8Rng,
) -> Transitions {
    let actions = config.world.layout().action_count();
    let batch = contexts(
        data,
        config.context.transitions_per_context,
        CODES_PER_TASK,
        actions,
        rng,
    );
    let codes = tch::no_grad(|| encode(model_encoder, &batch));
    let picks: Vec<i64> = (0..data.len())
        .map(|_| rand::Rng::random_range(rng, 0..CODES_PER_TASK as i64))
        .collect();
    let z = codes.index_select(0, &Tensor::from_slice(&picks));
    Transitions {
        obs: Tensor::cat(&[&data.obs, &z], 1),
        actions: data.actions.shallow_clone(),
        rewards: data.rewards.shallow_clone(),
        next_obs: Tensor::cat(&[&data.next_obs, &z], 1),
    }
}

/// The context learner meta-trained on `tasks` (each task's support and query sets together),
/// from the inits of `seed`. `on_step` and `keep_going` are CQL-pretrain's
/// ([`crate::pretrain::pretrain`]): `None` when told to stop.
pub fn meta_train<E>(
    config: &Config,
    tasks: &[MetaTask],
    seed: u64,
    on_step: OnStep,
    keep_going: impl FnMut(usize) -> Result<bool, E>,
) -> Result<Option<ContextModel>, E> {
    let data: Vec<Transitions> = tasks
        .iter()
        .map(|t| Transitions::concat([&t.support, &t.query]))
        .collect();
    let named: Vec<&TaskConfig> = tasks
        .iter()
        .map(|t| {
            config
                .task(&t.name)
                .expect("meta-train tasks are the config's")
        })
        .collect();
    let parameters = task_parameters(&named, &config.world);
    let encoder = train_encoder(config, &data, &parameters, seed);
    let mut rng = ChaCha8Rng::seed_from_u64(seed.wrapping_add(1));
    let coded: Vec<Transitions> = data
        .iter()
        .map(|d| with_codes(&encoder, d, config, &mut rng))
        .collect();
    let union = Transitions::concat(&coded);
    let w = &config.world;
    let q = QNetworkConfig::new(
        w.layout().observation_len() + config.context.latent,
        w.layout().action_count(),
        &config.learner.hidden,
    )
    .init(seed);
    let q = train_multi_task(q, &union, config, tasks, seed, on_step, keep_going)?;
    Ok(q.map(|q| ContextModel { encoder, q }))
}

/// What `uavmeta meta-train --learner context` made: the model's checkpoint and each meta-train
/// task's zero-shot return, its code read from the task's query set.
pub struct ContextRun {
    pub model: PathBuf,
    pub zero_shot: Vec<(String, f64)>,
}

/// Meta-trains the context learner on the datasets of `opts` and saves it as `OUT/context`
/// (with `OUT/config.toml`); a progress bar counts CQL-pretrain's meta-epochs of budget.
pub fn meta_train_to_dir(opts: &MetaTrainOptions) -> Result<ContextRun, MetaError> {
    let config = opts.config;
    let (tasks, meta_tasks) = load_tasks(config, opts.datasets, opts.seed)?;
    create_dir(opts.out_dir)?;
    write_file(&opts.out_dir.join("config.toml"), &config.to_toml_string())?;
    let bar = progress_bar(
        opts.progress,
        config.meta.meta_epochs as u64,
        "{bar:40} {pos}/{len} meta-epochs of budget eta {eta}",
    );
    let keep_going = |_| {
        bar.inc(1);
        Ok::<bool, MetaError>(true)
    };
    let model = meta_train(
        config,
        &meta_tasks,
        opts.seed,
        opts.on_step.clone(),
        keep_going,
    )?
    .expect("never told to stop");
    bar.finish_and_clear();
    let path = opts.out_dir.join("context");
    model.save(&path, config)?;
    let zero_shot = tasks
        .iter()
        .zip(&meta_tasks)
        .map(|(task, data)| {
            let policy = model.policy(&data.query);
            let ret = Evaluator::from_config(config, task)
                .evaluate(&policy)
                .ret
                .mean;
            (task.name.clone(), ret)
        })
        .collect();
    Ok(ContextRun {
        model: path,
        zero_shot,
    })
}
