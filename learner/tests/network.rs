//! The Q-network's shapes and seeded initialisation, and checkpoints: round trip, size mismatch,
//! truncated and corrupt files.

use std::path::Path;

use tch::{Device, Kind, Tensor};
use uavmeta_learner::checkpoint::{self, CheckpointError, CheckpointPaths};
use uavmeta_learner::qnet::{QNetwork, QNetworkConfig};
use uavmeta_proto::config::Config;

fn obs(rows: i64, d: i64, seed: i64) -> Tensor {
    tch::manual_seed(seed);
    Tensor::rand([rows, d], (Kind::Float, Device::Cpu))
}

#[test]
fn layout_and_pytorch_bounds() {
    let q = QNetworkConfig::new(12, 50, &[32, 16]).init(3);
    let shapes: Vec<Vec<i64>> = q.parameters().iter().map(Tensor::size).collect();
    assert_eq!(
        shapes,
        vec![
            vec![32, 12],
            vec![32],
            vec![16, 32],
            vec![16],
            vec![50, 16],
            vec![50]
        ]
    );
    assert_eq!(
        q.parameter_count(),
        32 * 12 + 32 + 16 * 32 + 16 + 50 * 16 + 50
    );
    // nn.Linear's default: U(-1/sqrt(fan_in), 1/sqrt(fan_in)) for weight and bias alike.
    for (i, p) in q.parameters().iter().enumerate() {
        let fan_in = [12.0f64, 12.0, 32.0, 32.0, 16.0, 16.0][i];
        let max = p.abs().max().double_value(&[]);
        assert!(
            max <= 1.0 / fan_in.sqrt() + 1e-7,
            "parameter {i}: max |w| = {max}"
        );
        // Spread over the interval, not collapsed: the largest draw is near the bound.
        assert!(max > 0.8 / fan_in.sqrt(), "parameter {i}: max |w| = {max}");
    }
    assert_eq!(q.forward(&obs(5, 12, 0)).size(), vec![5, 50]);
}

#[test]
fn initialisation_depends_on_the_seed_only() {
    let x = obs(4, 12, 1);
    let a = QNetworkConfig::new(12, 50, &[32, 32]).init(9);
    // Global libtorch RNG state must not matter.
    tch::manual_seed(12345);
    let _ = Tensor::rand([100], (Kind::Float, Device::Cpu));
    let b = QNetworkConfig::new(12, 50, &[32, 32]).init(9);
    let c = QNetworkConfig::new(12, 50, &[32, 32]).init(10);
    assert!(a.forward(&x).equal(&b.forward(&x)));
    assert!(!a.forward(&x).allclose(&c.forward(&x), 1e-3, 1e-3, false));
}

#[test]
fn functional_forward_carries_fast_weight_gradients() {
    let q = QNetworkConfig::new(6, 10, &[8]).init(1);
    let x = obs(3, 6, 2);
    assert!(QNetwork::forward_with(&q.parameters(), &x).equal(&q.forward(&x)));
    // Fast weights w' = w - 0.1 * g, as MAML's inner step forms them: the loss on w' must
    // differentiate back to w.
    let params = q.parameters();
    let inner = q.forward(&x).pow_tensor_scalar(2).mean(None);
    let grads = Tensor::run_backward(&[inner], &params, true, true);
    let fast: Vec<Tensor> = params
        .iter()
        .zip(&grads)
        .map(|(w, g)| w - g * 0.1)
        .collect();
    let outer = QNetwork::forward_with(&fast, &x).sum(Kind::Float);
    let meta_grads = Tensor::run_backward(&[outer], &params, false, false);
    assert!(meta_grads
        .iter()
        .all(|g| g.defined() && g.isfinite().all().int64_value(&[]) == 1));
    assert!(meta_grads[0].abs().sum(Kind::Float).double_value(&[]) > 0.0);
}

#[test]
fn copy_from_syncs_a_target() {
    let online = QNetworkConfig::new(6, 10, &[8]).init(1);
    let mut target = QNetworkConfig::new(6, 10, &[8]).init(2);
    let x = obs(3, 6, 3);
    assert!(!target.forward(&x).equal(&online.forward(&x)));
    target.copy_from(&online);
    assert!(target.forward(&x).equal(&online.forward(&x)));
    assert!(online.duplicate().forward(&x).equal(&online.forward(&x)));
}

fn config(devices: usize, hidden: &str) -> Config {
    Config::from_toml_str(
        &format!("[world]\ndevices = {devices}\n[learner]\nhidden = {hidden}\n"),
        "test.toml",
        &[],
    )
    .unwrap()
}

fn saved(dir: &Path) -> (QNetwork, std::path::PathBuf) {
    let cfg = config(4, "[16, 8]");
    let q = QNetworkConfig::for_world(&cfg.world, &cfg.learner.hidden).init(5);
    let path = dir.join("ckpt").join("epoch-7");
    let meta = checkpoint::save(&path, &q, "cql", 7, &cfg).unwrap();
    assert_eq!(
        (
            meta.algorithm.as_str(),
            meta.obs_len,
            meta.actions,
            meta.epoch
        ),
        ("cql", 6, 20, 7)
    );
    (q, path)
}

#[test]
fn checkpoint_round_trip() {
    let dir = tempfile::tempdir().unwrap();
    let (q, path) = saved(dir.path());
    let cfg = config(4, "[16, 8]");
    let (loaded, meta) = checkpoint::load(&path, &cfg).unwrap();
    let x = obs(5, 6, 4);
    assert!(loaded.forward(&x).equal(&q.forward(&x)));
    assert_eq!(meta.hidden, vec![16, 8]);
    assert_eq!(meta.world_hash, cfg.world_hash());
    // The run's full config is saved beside it and reads back to the same config.
    let paths = CheckpointPaths::new(&path);
    let again = Config::load(&paths.config, &[]).unwrap();
    assert_eq!(again.world, cfg.world);
    assert_eq!(again.learner, cfg.learner);
    // No temporary files are left behind.
    let leftovers: Vec<_> = std::fs::read_dir(paths.weights.parent().unwrap())
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|n| n.contains(".tmp-"))
        .collect();
    assert!(leftovers.is_empty(), "{leftovers:?}");
}

#[test]
fn checkpoint_size_mismatch_is_a_clear_error() {
    let dir = tempfile::tempdir().unwrap();
    let (_, path) = saved(dir.path());
    let err = checkpoint::load(&path, &config(5, "[16, 8]"))
        .err()
        .expect("devices differ");
    assert!(
        matches!(
            err,
            CheckpointError::SizeMismatch {
                key: "world.devices",
                ..
            }
        ),
        "{err}"
    );
    let text = err.to_string();
    assert!(
        text.contains("epoch-7.json")
            && text.contains("world.devices")
            && text.contains("test.toml"),
        "{text}"
    );
    let err = checkpoint::load(&path, &config(4, "[16, 16]"))
        .err()
        .expect("hidden differs");
    assert!(
        err.to_string().contains("learner.hidden") && err.to_string().contains("[16, 8]"),
        "{err}"
    );
}

#[test]
fn truncated_or_corrupt_checkpoint_names_the_file() {
    let dir = tempfile::tempdir().unwrap();
    let (_, path) = saved(dir.path());
    let cfg = config(4, "[16, 8]");
    let weights = CheckpointPaths::new(&path).weights;
    let bytes = std::fs::read(&weights).unwrap();

    std::fs::write(&weights, &bytes[..bytes.len() / 2]).unwrap();
    let err = checkpoint::load(&path, &cfg).err().expect("truncated");
    let text = err.to_string();
    assert!(matches!(err, CheckpointError::Truncated { .. }), "{text}");
    assert!(
        text.contains("epoch-7.safetensors")
            && text.contains(&format!("offset {}", bytes.len() / 2)),
        "{text}"
    );

    let mut flipped = bytes.clone();
    let last = flipped.len() - 3;
    flipped[last] ^= 0x40;
    std::fs::write(&weights, &flipped).unwrap();
    let err = checkpoint::load(&path, &cfg).err().expect("corrupt");
    assert!(
        matches!(err, CheckpointError::Corrupt { .. })
            && err.to_string().contains("epoch-7.safetensors"),
        "{err}"
    );

    std::fs::write(&weights, &bytes).unwrap();
    let meta = CheckpointPaths::new(&path).meta;
    let text = std::fs::read_to_string(&meta).unwrap();
    std::fs::write(&meta, &text[..text.len() / 2]).unwrap();
    let err = checkpoint::load(&path, &cfg)
        .err()
        .expect("corrupt metadata");
    assert!(
        matches!(err, CheckpointError::Meta { .. }) && err.to_string().contains("epoch-7.json"),
        "{err}"
    );
    let cause = std::error::Error::source(&err)
        .map(|c| c.to_string())
        .unwrap_or_default();
    assert!(
        cause.contains("line"),
        "serde_json's position is kept in the cause: {err}: {cause}"
    );
}

#[test]
fn checkpoint_of_another_format_version_is_refused_by_name() {
    let dir = tempfile::tempdir().unwrap();
    let (_, path) = saved(dir.path());
    let meta_path = CheckpointPaths::new(&path).meta;
    let mut meta: serde_json::Value =
        serde_json::from_slice(&std::fs::read(&meta_path).unwrap()).unwrap();
    meta["format_version"] = serde_json::json!(999);
    std::fs::write(&meta_path, serde_json::to_vec(&meta).unwrap()).unwrap();

    let err = checkpoint::read_meta(&path).expect_err("version differs");
    assert!(
        matches!(err, CheckpointError::FormatVersion { found: 999, .. }),
        "{err}"
    );
    assert!(err.to_string().contains("epoch-7.json"), "{err}");
    let err = checkpoint::load(&path, &config(4, "[16, 8]"))
        .err()
        .expect("version differs");
    assert!(
        matches!(err, CheckpointError::FormatVersion { found: 999, .. }),
        "{err}"
    );
}

/// The heads a checkpoint's metadata claims must be its algorithm's: a forged count, which would
/// size the network (a million heads is gigabytes), is refused by name before anything is built.
#[test]
fn checkpoint_heads_other_than_the_algorithms_are_refused_by_name() {
    let dir = tempfile::tempdir().unwrap();
    let (_, path) = saved(dir.path());
    let meta_path = CheckpointPaths::new(&path).meta;
    let original: serde_json::Value =
        serde_json::from_slice(&std::fs::read(&meta_path).unwrap()).unwrap();
    for (algorithm, heads, expected) in [("cql", 2, 1), ("cql", 1_000_000, 1), ("bcq", 1, 2)] {
        let mut meta = original.clone();
        meta["algorithm"] = serde_json::json!(algorithm);
        meta["heads"] = serde_json::json!(heads);
        std::fs::write(&meta_path, serde_json::to_vec(&meta).unwrap()).unwrap();
        let err = checkpoint::load(&path, &config(4, "[16, 8]"))
            .err()
            .expect("the heads differ from the algorithm's");
        assert!(
            matches!(err, CheckpointError::Heads { found, expected: e, .. } if found == heads && e == expected),
            "{err}"
        );
        let message = err.to_string();
        assert!(
            message.contains("epoch-7.json") && message.contains(algorithm),
            "{message}"
        );
    }
}

/// A network with its last inputs fixed (the context learner's policy for one task code) gives
/// the outputs of the full network on the observation with the code appended.
#[test]
fn a_network_conditioned_on_fixed_inputs_matches_the_full_network() {
    let full = QNetworkConfig::new(5, 4, &[16, 16]).init(3);
    let code = Tensor::from_slice(&[0.3f32, -1.2]);
    let obs = Tensor::from_slice(&[0.1f32, 0.9, 0.5, 0.2, 0.7, 0.4]).view([2, 3]);
    let appended = Tensor::cat(&[obs.shallow_clone(), code.unsqueeze(0).repeat([2, 1])], 1);
    let conditioned = full.conditioned_on(&code);
    assert_eq!(conditioned.obs_len(), 3);
    let gap = (conditioned.forward(&obs) - full.forward(&appended))
        .abs()
        .max()
        .double_value(&[]);
    assert!(gap < 1e-5, "{gap}");
}

/// A network gaining a head (BCQ's imitation logits) keeps its Q-values, and the new head starts
/// ordered as they are but at a fresh layer's scale, whatever the Q-values' own: copied at the
/// scale of a w0 meta-trained where lambda is large (hundreds), it made BCQ from w0 collapse.
#[test]
fn a_new_head_starts_ordered_as_the_q_values_at_a_fresh_layers_scale() {
    let x = obs(16, 6, 3);
    for factor in [1.0, 30.0] {
        let q = QNetworkConfig::new(6, 10, &[8]).init(1);
        tch::no_grad(|| {
            for (_, mut v) in q.vs.variables() {
                let _ = v.g_mul_scalar_(factor);
            }
        });
        let values = q.forward(&x);
        let two = q.with_heads(2).forward(&x);
        assert!(two.narrow(-1, 0, 10).equal(&values), "factor {factor}");
        let logits = two.narrow(-1, 10, 10);
        assert!(
            logits.argmax(-1, false).equal(&values.argmax(-1, false)),
            "factor {factor}"
        );
        // Scaled by the ratio of weight sizes: as large as the Q-values for a fresh network,
        // a small fraction of them for large ones (the old copy kept them equal).
        let size = |t: &Tensor| t.abs().max().double_value(&[]);
        let ratio = size(&logits) / size(&values);
        match factor == 1.0 {
            true => assert!((0.3..3.0).contains(&ratio), "factor {factor}: {ratio}"),
            false => assert!(ratio < 0.1, "factor {factor}: {ratio}"),
        }
    }
}
