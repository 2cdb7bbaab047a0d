//! A population: N Q-networks of one shape trained in lockstep as one computation.
//!
//! Each parameter of [`QNetwork`] gains a leading member dimension (`layer{i}.weight` is
//! `[N, fan_out, fan_in]`), so a forward pass is one batched matrix product per layer for all
//! members (feature-major, so that each weight gradient lands in its own layout) and one Adam
//! step updates every member. Members never mix:
//!
//! - the loss is the sum over members of each member's own mean loss, so the gradient that
//!   reaches member i's weights is exactly the gradient of its own loss;
//! - Adam is elementwise, so each member has its own first and second moments;
//! - gradient-norm clipping ([`QPopulation::clip_grad_norm`]) takes each member's own norm;
//! - each member is initialised from its own seed, exactly as [`QNetworkConfig::init`] would.
//!
//! A population of one computes what a single [`QNetwork`] does, bit for bit
//! (`actors/tests/population.rs` checks it for the online DQN agent); with N members each follows
//! the trajectory of its own separate run up to float rounding. This is the PureJaxRL / EnvPool
//! way of filling a core with small networks: at [256, 256] and batch 64 one learner spends most
//! of its time on per-operation overhead, N stacked learners share it (docs/BENCHMARKS.md,
//! "Populations").

use tch::{nn, Device, Tensor};

use crate::qnet::{QNetwork, QNetworkConfig};

/// A `run.device` libtorch cannot use.
#[derive(Debug, thiserror::Error)]
#[error(
    "run.device = {device:?}: libtorch sees {cuda} CUDA device(s) (this libtorch build: cuda available = {available}); \
     expected cpu, or cuda / cuda:N below that count"
)]
pub struct DeviceError {
    pub device: String,
    pub cuda: usize,
    pub available: bool,
}

/// The libtorch device `run.device` names (`cpu`, `cuda`, `cuda:N`; the config checked the
/// form), refused when libtorch has no such GPU.
pub fn device(spec: &str) -> Result<Device, DeviceError> {
    let index = match spec {
        "cpu" => return Ok(Device::Cpu),
        "cuda" => Some(0),
        other => other
            .strip_prefix("cuda:")
            .and_then(|i| i.parse::<usize>().ok()),
    };
    let cuda = tch::Cuda::device_count().max(0) as usize;
    match index {
        Some(i) if i < cuda => Ok(Device::Cuda(i)),
        _ => Err(DeviceError {
            device: spec.to_string(),
            cuda,
            available: tch::Cuda::is_available(),
        }),
    }
}

/// N Q-networks of one architecture with stacked parameters.
pub struct QPopulation {
    /// Every stacked parameter under the names `layer{i}.weight` / `layer{i}.bias`, as in
    /// [`QNetwork`] but with a leading member dimension; the optimiser works on it.
    pub vs: nn::VarStore,
    /// `[w1, b1, w2, b2, ..]`, each `[N, ..]`, shallow handles onto the variables of `vs`.
    params: Vec<Tensor>,
    config: QNetworkConfig,
    members: usize,
}

impl QPopulation {
    /// One member per seed, member i initialised as `config.init(seeds[i])`, on `device`.
    ///
    /// # Panics
    /// If `seeds` is empty: a population has at least one member.
    pub fn init(config: &QNetworkConfig, seeds: &[u64], device: Device) -> Self {
        let networks: Vec<QNetwork> = seeds.iter().map(|&s| config.init(s)).collect();
        Self::from_networks(&networks, device)
    }

    /// One member per network, member i a copy of `networks[i]` (a checkpoint to fine-tune, say),
    /// on `device`.
    ///
    /// # Panics
    /// If `networks` is empty or its networks differ in architecture: the caller groups members
    /// by shape.
    pub fn from_networks(networks: &[QNetwork], device: Device) -> Self {
        assert!(
            !networks.is_empty(),
            "a population needs at least one member"
        );
        let config = networks[0].config().clone();
        assert!(
            networks.iter().all(|q| *q.config() == config),
            "a population's members share one architecture"
        );
        let vs = nn::VarStore::new(device);
        let root = vs.root();
        let layers = networks[0].parameters().len() / 2;
        let mut params = Vec::with_capacity(2 * layers);
        for i in 0..layers {
            let layer = &root / format!("layer{i}");
            for (j, name) in ["weight", "bias"].into_iter().enumerate() {
                let stacked = Tensor::stack(
                    &networks
                        .iter()
                        .map(|q| q.parameters()[2 * i + j].detach())
                        .collect::<Vec<_>>(),
                    0,
                )
                .to_device(device);
                params.push(layer.var_copy(name, &stacked));
            }
        }
        Self {
            vs,
            params,
            config,
            members: networks.len(),
        }
    }

    /// Q-values of every member: `obs` [N, B, obs_len] (member i's rows at `obs[i]`) ->
    /// [N, B, actions].
    ///
    /// A population of one runs the single network's plain matrix products on views of its
    /// parameters: libtorch's batched product with a batch of one sums a small layer's weight
    /// gradient in another order (one ulp apart on the first layer), and a population of one is
    /// to be the single learner bit for bit.
    pub fn forward(&self, obs: &Tensor) -> Tensor {
        if self.members == 1 {
            let single: Vec<Tensor> = self.params.iter().map(|p| p.squeeze_dim(0)).collect();
            return QNetwork::forward_with(&single, &obs.squeeze_dim(0)).unsqueeze(0);
        }
        stacked_forward(&self.params, obs)
    }

    /// Each member's greedy actions on its own rows: `obs` [N, B, obs_len] -> [N, B] i64,
    /// without a graph.
    pub fn greedy(&self, obs: &Tensor) -> Tensor {
        tch::no_grad(|| self.forward(obs).argmax(-1, false))
    }

    /// The stacked parameters `[w1, b1, ..]`, each `[N, ..]` (handles that require grad).
    pub fn parameters(&self) -> Vec<Tensor> {
        self.params.iter().map(Tensor::shallow_clone).collect()
    }

    /// Panics naming `operation` unless `other` has this population's architecture and size.
    fn assert_same_shape(&self, other: &QPopulation, operation: &str) {
        assert_eq!(
            (&self.config, self.members),
            (&other.config, other.members),
            "{operation} between populations of different shapes"
        );
    }

    /// Overwrites every member's parameters with `other`'s: the hard target-network update.
    ///
    /// # Panics
    /// If the two populations differ in architecture or size; a target population is always
    /// built from its online population.
    pub fn copy_from(&mut self, other: &QPopulation) {
        self.assert_same_shape(other, "copy_from");
        tch::no_grad(|| {
            for (dst, src) in self.params.iter_mut().zip(&other.params) {
                dst.copy_(src);
            }
        });
    }

    /// Polyak averaging of every member toward `other`'s same member, as
    /// [`QNetwork::average_toward`]: self <- decay * self + (1 - decay) * other.
    ///
    /// # Panics
    /// If the two populations differ in architecture or size.
    pub fn average_toward(&mut self, other: &QPopulation, decay: f64) {
        self.assert_same_shape(other, "average_toward");
        tch::no_grad(|| {
            for (dst, src) in self.params.iter_mut().zip(&other.params) {
                let _ = dst.g_mul_scalar_(decay).g_add_(&(src * (1.0 - decay)));
            }
        });
    }

    /// A new population of the same shape with a copy of this one's parameter values.
    pub fn duplicate(&self) -> QPopulation {
        let device = self.vs.device();
        let mut copy = Self::init(&self.config, &vec![0; self.members], device);
        copy.copy_from(self);
        copy
    }

    /// A copy of member `i` as a single network on the CPU (to evaluate, select or checkpoint).
    ///
    /// # Panics
    /// If `i` is not below [`QPopulation::members`].
    pub fn member(&self, i: usize) -> QNetwork {
        assert!(
            i < self.members,
            "member {i} of a population of {}",
            self.members
        );
        let q = self.config.init(0);
        tch::no_grad(|| {
            for (dst, src) in q.parameters().iter_mut().zip(&self.params) {
                dst.copy_(&src.get(i as i64).to_device(Device::Cpu));
            }
        });
        q
    }

    /// Clips each member's gradient to norm `max`, as `tch`'s (and PyTorch's) `clip_grad_norm`
    /// does for one network: member i's gradients are scaled by `max / (norm_i + 1e-6)` when that
    /// is below 1, `norm_i` the 2-norm of all its parameters' gradients together.
    pub fn clip_grad_norm(&self, max: f64) {
        tch::no_grad(|| {
            let grads: Vec<Tensor> = self.params.iter().map(Tensor::grad).collect();
            // Per parameter, each member's norm: [P, N]; over parameters: [N].
            let norms: Vec<Tensor> = grads
                .iter()
                .map(|g| {
                    g.flatten(1, -1)
                        .norm_scalaropt_dim(2, [1].as_slice(), false)
                })
                .collect();
            let total = Tensor::stack(&norms, 0).norm_scalaropt_dim(2, [0].as_slice(), false);
            let total = Vec::<f32>::try_from(total.to_device(Device::Cpu))
                .expect("a norm per member is a float vector");
            let coefs: Vec<f32> = total
                .iter()
                .map(|&norm| {
                    let coef = max / (f64::from(norm) + 1e-6);
                    if coef < 1.0 {
                        coef as f32
                    } else {
                        1.0
                    }
                })
                .collect();
            if coefs.iter().all(|&c| c == 1.0) {
                return;
            }
            let coefs = Tensor::from_slice(&coefs).to_device(self.vs.device());
            for mut g in grads {
                let shape: Vec<i64> = std::iter::once(self.members as i64)
                    .chain(std::iter::repeat_n(1, g.dim() - 1))
                    .collect();
                let _ = g.g_mul_(&coefs.view(shape.as_slice()));
            }
        })
    }

    /// Its members' architecture.
    pub fn config(&self) -> &QNetworkConfig {
        &self.config
    }

    /// How many networks it holds (N).
    pub fn members(&self) -> usize {
        self.members
    }

    /// The device its tensors live on.
    pub fn device(&self) -> Device {
        self.vs.device()
    }

    /// Floats of one member's parameters.
    pub fn member_parameter_count(&self) -> usize {
        self.params.iter().map(Tensor::numel).sum::<usize>() / self.members
    }
}

/// The members' forward pass, feature-major: the activations are `[N, features, B]` and each
/// layer is `h <- W h + b` with `W` as stored, `[N, fan_out, fan_in]`. Autograd then gives each
/// weight's gradient (`dh h_prev^T`) in the weight's own layout. The row-major form
/// (`x W^T + b`, [`QNetwork::forward_with`]'s, which MAML uses) gives it transposed, and libtorch
/// copies every weight gradient into the parameter's layout at every step: a quarter of an N = 8
/// step on an Intel Xeon (docs/BENCHMARKS.md, "Populations"). `obs` [N, B, obs_len] -> [N, B,
/// actions] (a transposed view).
fn stacked_forward(params: &[Tensor], obs: &Tensor) -> Tensor {
    let layers = params.len() / 2;
    let mut h = obs.transpose(1, 2);
    for (i, wb) in params.chunks_exact(2).enumerate() {
        h = wb[1].unsqueeze(2).baddbmm(&wb[0], &h, 1, 1);
        if i + 1 < layers {
            h = h.relu();
        }
    }
    h.transpose(1, 2)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_device_is_refused_by_name_where_libtorch_has_no_gpu() {
        assert_eq!(device("cpu").unwrap(), Device::Cpu);
        if tch::Cuda::device_count() == 0 {
            for spec in ["cuda", "cuda:1"] {
                let error = device(spec).unwrap_err().to_string();
                assert!(
                    error.contains(&format!("run.device = {spec:?}")) && error.contains("0 CUDA"),
                    "{error}"
                );
            }
        }
    }
}
