//! The Q-network of docs/MODEL.md section 5: an MLP from the normalised observation (2 + K values)
//! through ReLU hidden layers to one Q-value per action (5K). An algorithm that learns more than
//! Q-values (discrete BCQ's imitation logits) asks for more heads: blocks of 5K outputs after the
//! Q-values, on the same hidden layers, and says how the network acts on them.
//!
//! The parameters live in a `VarStore` (for Adam and safetensors checkpoints) and are also kept in
//! layer order, so that the same forward pass runs on an explicit parameter list: MAML's fast
//! weights `w_i = w0 - eta_inner * grad` are plain tensors, not variables of a store.

use std::sync::Arc;

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use tch::{nn, Device, Tensor};
use uavmeta_proto::config::WorldConfig;

/// The architecture of a [`QNetwork`]: `obs_len -> hidden[0] -> .. -> heads * actions`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct QNetworkConfig {
    pub obs_len: usize,
    pub actions: usize,
    pub hidden: Vec<usize>,
    /// Blocks of `actions` outputs: the Q-values first, then what the algorithm adds (1 for
    /// every algorithm but discrete BCQ).
    pub heads: usize,
}

impl QNetworkConfig {
    pub fn new(obs_len: usize, actions: usize, hidden: &[usize]) -> Self {
        Self {
            obs_len,
            actions,
            hidden: hidden.to_vec(),
            heads: 1,
        }
    }

    /// A network for `world`'s observations and actions with hidden layers of widths `hidden`
    /// (`learner.hidden`, or `collect.dqn.hidden` for the online DQN agent).
    pub fn for_world(world: &WorldConfig, hidden: &[usize]) -> Self {
        Self::new(
            world.layout().observation_len(),
            world.layout().action_count(),
            hidden,
        )
    }

    /// A network of this architecture, initialised from `seed` alone.
    ///
    /// The scheme is PyTorch's `nn.Linear` default (Kaiming-uniform with a = sqrt(5), which for
    /// both weight and bias is U(-1/sqrt(fan_in), 1/sqrt(fan_in))), but the draws come from a
    /// ChaCha8 stream rather than libtorch's global generator, so two networks built with the
    /// same seed are identical whatever else the process has drawn, on any thread.
    pub fn init(&self, seed: u64) -> QNetwork {
        let vs = nn::VarStore::new(Device::Cpu);
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let widths: Vec<usize> = std::iter::once(self.obs_len)
            .chain(self.hidden.iter().copied())
            .chain(std::iter::once(self.heads * self.actions))
            .collect();
        let mut params = Vec::with_capacity(2 * (widths.len() - 1));
        let root = vs.root();
        for (i, pair) in widths.windows(2).enumerate() {
            let (fan_in, fan_out) = (pair[0], pair[1]);
            let bound = 1.0 / (fan_in as f32).sqrt();
            let mut uniform = |n: usize| -> Vec<f32> {
                (0..n).map(|_| rng.random_range(-bound..=bound)).collect()
            };
            // weight: [fan_out, fan_in], as torch.nn.Linear stores it (y = x W^T + b).
            let w = Tensor::from_slice(&uniform(fan_out * fan_in))
                .view([fan_out as i64, fan_in as i64]);
            // bias: [fan_out].
            let b = Tensor::from_slice(&uniform(fan_out));
            // `layer{i}.weight`: the path separator joins the layer and the variable name.
            let layer = &root / format!("layer{i}");
            params.push(layer.var_copy("weight", &w));
            params.push(layer.var_copy("bias", &b));
        }
        QNetwork {
            vs,
            params,
            config: self.clone(),
            acting: None,
        }
    }
}

/// How a network's outputs `[.., heads * A]` become the values its greedy action maximises,
/// `[.., A]`: the algorithm's rule, where it has one (`OfflineAlgorithm::acting`).
pub type Acting = Arc<dyn Fn(&Tensor) -> Tensor + Send + Sync>;

/// The Q-values `[.., A]` among a network's outputs `[.., heads * A]`: its first block.
pub fn q_values(outputs: &Tensor, heads: usize) -> Tensor {
    head(outputs, heads, 0)
}

/// Block `index` `[.., A]` of a network's outputs `[.., heads * A]`.
pub fn head(outputs: &Tensor, heads: usize, index: usize) -> Tensor {
    if heads == 1 {
        return outputs.shallow_clone();
    }
    let width = outputs
        .size()
        .last()
        .copied()
        .expect("outputs have a last dimension")
        / heads as i64;
    outputs.narrow(-1, index as i64 * width, width)
}

/// An MLP Q-function `Q(s, .)`.
pub struct QNetwork {
    /// Holds every parameter under the names `layer{i}.weight` / `layer{i}.bias`; optimisers and
    /// checkpoints work on it.
    pub vs: nn::VarStore,
    /// `[w1, b1, w2, b2, ..]`, shallow handles onto the variables of `vs`, in layer order.
    params: Vec<Tensor>,
    config: QNetworkConfig,
    /// The algorithm's acting rule; `None` acts greedily on the Q-values.
    acting: Option<Acting>,
}

impl QNetwork {
    /// Q-values of every action: `obs` [B, obs_len] f32 (normalised) -> [B, actions].
    pub fn forward(&self, obs: &Tensor) -> Tensor {
        Self::forward_with(&self.params, obs)
    }

    /// The parameters `[w1, b1, w2, b2, ..]` in layer order (handles that share storage with the
    /// network's variables and require grad).
    pub fn parameters(&self) -> Vec<Tensor> {
        self.params.iter().map(Tensor::shallow_clone).collect()
    }

    /// The same MLP on an explicit parameter list laid out as [`QNetwork::parameters`] returns
    /// it: `obs` [B, obs_len] -> [B, actions]. Gradients flow into whatever `params` came from,
    /// which is how MAML differentiates the query loss through the inner-loop updates.
    ///
    /// With stacked parameters (each with a leading dimension T: T networks, MAML's fast weights
    /// of T tasks) `obs` is [T, B, obs_len] and network t sees `obs[t]`: [T, B, actions], one
    /// batched matrix product per layer for all T. Unstacked parameters on [T, B, obs_len] are
    /// one network applied to every row.
    pub fn forward_with(params: &[Tensor], obs: &Tensor) -> Tensor {
        let layers = params.len() / 2;
        let mut x = obs.shallow_clone();
        for (i, wb) in params.chunks_exact(2).enumerate() {
            let (w, b) = (&wb[0], &wb[1]);
            x = if w.dim() == 3 {
                // [T, B, fan_in] @ [T, fan_in, fan_out] + [T, 1, fan_out]
                b.unsqueeze(1).baddbmm(&x, &w.transpose(1, 2), 1, 1)
            } else {
                // [.., fan_in] -> [.., fan_out]
                x.linear(w, Some(b))
            };
            if i + 1 < layers {
                x = x.relu();
            }
        }
        x
    }

    /// Greedy actions `argmax_a Q(s, a)`, or the algorithm's acting rule's argmax: `obs`
    /// [B, obs_len] -> [B] i64, computed without a graph.
    pub fn greedy(&self, obs: &Tensor) -> Tensor {
        tch::no_grad(|| {
            let outputs = self.forward(obs);
            let values = match &self.acting {
                Some(acting) => acting(&outputs),
                None => q_values(&outputs, self.config.heads),
            };
            values.argmax(-1, false)
        })
    }

    /// Acts by `acting` from now on (`None`: greedily on the Q-values).
    pub fn set_acting(&mut self, acting: Option<Acting>) {
        self.acting = acting;
    }

    /// This network with `heads` blocks of outputs: its Q-value block first and, in every other
    /// block, that block scaled to a freshly initialised layer's size (or the others dropped), so
    /// a network trained by one algorithm starts another's training with its Q-values and its
    /// hidden layers unchanged. The other heads (BCQ's imitation logits) start ordered as the
    /// Q-values but at a new layer's scale: copied at the Q-values' own, hundreds where lambda is
    /// large, they made BCQ from w0 collapse (docs/EXPERIMENTS.md B8).
    pub fn with_heads(&self, heads: usize) -> QNetwork {
        let config = QNetworkConfig {
            heads,
            ..self.config.clone()
        };
        let mut q = config.init(0);
        let last = self.params.len() - 2;
        let actions = self.config.actions as i64;
        // The output weights' RMS of the new network's own init over that of this one's.
        let scale = rms(&q.params[last].narrow(0, 0, actions))
            / rms(&self.params[last].narrow(0, 0, actions)).max(f64::MIN_POSITIVE);
        tch::no_grad(|| {
            for (i, (dst, src)) in q.params.iter_mut().zip(&self.params).enumerate() {
                if i < last {
                    dst.copy_(src);
                } else {
                    let block = src.narrow(0, 0, actions);
                    let scaled = &block * scale;
                    let mut blocks: Vec<&Tensor> = vec![&block];
                    blocks.extend(std::iter::repeat_n(&scaled, heads - 1));
                    dst.copy_(&Tensor::cat(&blocks, 0));
                }
            }
        });
        q.acting = self.acting.clone();
        q
    }

    /// Overwrites this network's parameters with `other`'s: the hard target-network update.
    ///
    /// # Panics
    /// If the two networks have different architectures; a target network is always built from
    /// the same sizes as its online network.
    pub fn copy_from(&mut self, other: &QNetwork) {
        assert_eq!(
            self.config, other.config,
            "copy_from between Q-networks of different architectures"
        );
        tch::no_grad(|| {
            for (dst, src) in self.params.iter_mut().zip(&other.params) {
                dst.copy_(src);
            }
        });
    }

    /// Polyak averaging: self <- decay * self + (1 - decay) * other.
    pub fn average_toward(&mut self, other: &QNetwork, decay: f64) {
        assert_eq!(
            self.config, other.config,
            "average_toward between Q-networks of different architectures"
        );
        tch::no_grad(|| {
            for (dst, src) in self.params.iter_mut().zip(&other.params) {
                let _ = dst.g_mul_scalar_(decay).g_add_(&(src * (1.0 - decay)));
            }
        });
    }

    /// A new network with the same architecture and a copy of this one's parameter values.
    pub fn duplicate(&self) -> QNetwork {
        let mut copy = self.config.init(0);
        copy.copy_from(self);
        copy.acting = self.acting.clone();
        copy
    }

    /// The network with its last inputs fixed to `values` [n]: an MLP on the first
    /// `obs_len - n` inputs that gives the same outputs, the fixed inputs' share of the first
    /// layer, `W[:, obs_len - n..] values`, folded into its bias. It acts as this one does.
    pub fn conditioned_on(&self, values: &Tensor) -> QNetwork {
        let n = values.size()[0];
        let kept = self.config.obs_len as i64 - n;
        assert!(
            kept >= 1,
            "conditioned_on fixes fewer inputs than the network has"
        );
        let mut net = QNetworkConfig {
            obs_len: kept as usize,
            ..self.config.clone()
        }
        .init(0);
        tch::no_grad(|| {
            let (w, b) = (&self.params[0], &self.params[1]);
            net.params[0].copy_(&w.narrow(1, 0, kept));
            net.params[1].copy_(&(b + w.narrow(1, kept, n).mv(values)));
            for (dst, src) in net.params.iter_mut().zip(&self.params).skip(2) {
                dst.copy_(src);
            }
        });
        net.acting = self.acting.clone();
        net
    }

    /// Its architecture.
    pub fn config(&self) -> &QNetworkConfig {
        &self.config
    }

    pub fn obs_len(&self) -> usize {
        self.config.obs_len
    }

    pub fn actions(&self) -> usize {
        self.config.actions
    }

    pub fn hidden(&self) -> &[usize] {
        &self.config.hidden
    }

    /// Number of scalar parameters.
    pub fn parameter_count(&self) -> usize {
        self.params.iter().map(Tensor::numel).sum()
    }

    /// The largest absolute difference between a parameter of this network and the same
    /// parameter of `other` (of the same architecture): 0 when they are equal bit for bit.
    pub fn max_abs_difference(&self, other: &QNetwork) -> f64 {
        tch::no_grad(|| {
            self.params
                .iter()
                .zip(&other.params)
                .map(|(a, b)| (a - b).abs().max().double_value(&[]))
                .fold(0.0, f64::max)
        })
    }
}

/// The root mean square of a tensor's values.
fn rms(t: &Tensor) -> f64 {
    t.square().mean(tch::Kind::Double).sqrt().double_value(&[])
}

#[cfg(test)]
impl QNetworkConfig {
    /// A network of this architecture whose Q-values are `bias` in every state: zero weights, the
    /// output bias `bias` (one value per action).
    pub(crate) fn constant(&self, bias: &[f32]) -> QNetwork {
        let q = self.init(0);
        let mut params = q.parameters();
        tch::no_grad(|| {
            for p in &mut params {
                let _ = p.zero_();
            }
            let last = params.last_mut().expect("a network has layers");
            last.copy_(&Tensor::from_slice(bias));
        });
        q
    }
}
