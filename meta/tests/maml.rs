//! MAML correctness: the meta-gradient against finite differences, first versus second order,
//! meta-training lowering the meta-loss on held-out query data, a resumed meta-training continuing
//! exactly as an uninterrupted one, and `meta.huber` reaching MAML's losses.

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use tch::{Kind, Tensor};
use uavmeta_learner::checkpoint;
use uavmeta_learner::dqn::TdConfig;
use uavmeta_learner::qnet::QNetworkConfig;
use uavmeta_learner::transitions::Transitions;
use uavmeta_meta::maml::{Maml, MamlConfig, MetaTask, StepSize, TaskShots};
use uavmeta_proto::config::{Config, LearnerConfig, MetaConfig};
use uavmeta_proto::method::Algo;

const OBS: usize = 3;
const ACTIONS: usize = 5;

/// These networks are tiny: libtorch's intra-op threads only contend with each other (and with
/// everything else on a shared machine), which made this file 20x slower.
fn single_threaded() {
    tch::set_num_threads(1);
}

fn config(inner_loss: Algo, inner_steps: usize, first_order: bool) -> MamlConfig {
    MamlConfig {
        meta: MetaConfig {
            inner_loss,
            alpha: 1.0,
            tasks_per_meta_epoch: 0,
            support_batch_size: 8,
            query_batch_size: 8,
            inner_steps,
            // Large enough that the second-order term is far above finite-difference noise.
            eta_inner: 0.3,
            eta_outer: 1e-2,
            meta_epochs: 1,
            first_order,
            learn_inner_lr: false,
            target_update_meta_epochs: 1,
            outer_steps_per_meta_epoch: 1,
            average_decay_per_outer_step: 0.0,
            ..MetaConfig::default()
        },
        td: TdConfig::eq7(0.9),
        learner: LearnerConfig::default(),
    }
}

/// `rows` random transitions of a task whose reward weighs the observation by `lambda`, in `kind`.
fn batch(rows: usize, lambda: f64, kind: Kind, rng: &mut ChaCha8Rng) -> Transitions {
    let mut uniform =
        |n: usize| -> Vec<f64> { (0..n).map(|_| rng.random_range(0.0..1.0)).collect() };
    let obs = uniform(rows * OBS);
    let next_obs = uniform(rows * OBS);
    let actions: Vec<i64> = uniform(rows)
        .iter()
        .map(|u| (u * ACTIONS as f64) as i64)
        .collect();
    let rewards: Vec<f64> = (0..rows)
        .map(|i| {
            -(obs[i * OBS] + lambda * obs[i * OBS + 1]) * (1.0 + actions[i] as f64 / ACTIONS as f64)
        })
        .collect();
    let shape = [rows as i64, OBS as i64];
    Transitions {
        obs: Tensor::from_slice(&obs).view(shape).to_kind(kind),
        actions: Tensor::from_slice(&actions),
        rewards: Tensor::from_slice(&rewards).to_kind(kind),
        next_obs: Tensor::from_slice(&next_obs).view(shape).to_kind(kind),
    }
}

fn shots(tasks: usize, rows: usize, kind: Kind, rng: &mut ChaCha8Rng) -> Vec<TaskShots> {
    (0..tasks)
        .map(|i| {
            let lambda = i as f64;
            TaskShots {
                support: batch(rows, lambda, kind, rng),
                query: batch(rows, lambda, kind, rng),
            }
        })
        .collect()
}

/// The parameters of a seeded network as f64 leaves that require grad.
fn leaves(seed: u64) -> Vec<Tensor> {
    QNetworkConfig::new(OBS, ACTIONS, &[6])
        .init(seed)
        .parameters()
        .iter()
        .map(|p| p.to_kind(Kind::Double).detach().set_requires_grad(true))
        .collect()
}

/// Eq. 15's value at `w0`.
fn meta_loss(
    c: &MamlConfig,
    w0: &[Tensor],
    step: StepSize,
    target: &[Tensor],
    tasks: &[TaskShots],
) -> f64 {
    tasks
        .iter()
        .map(|t| {
            c.task_loss(&c.adapt(w0, step, target, &t.support), target, &t.query)
                .double_value(&[])
        })
        .sum()
}

/// Fresh leaves that require grad, with the values of `tensors`.
fn fresh_leaves(tensors: &[Tensor]) -> Vec<Tensor> {
    tensors
        .iter()
        .map(|t| t.detach().copy().set_requires_grad(true))
        .collect()
}

/// What `backward_meta_loss` leaves in the gradients of fresh copies of `w0`, flattened.
fn meta_gradient(
    c: &MamlConfig,
    w0: &[Tensor],
    target: &[Tensor],
    tasks: &[TaskShots],
) -> Vec<f64> {
    let w0 = fresh_leaves(w0);
    c.backward_meta_loss(&w0, StepSize::Shared, target, tasks);
    flatten(&w0.iter().map(Tensor::grad).collect::<Vec<_>>())
}

fn flatten(tensors: &[Tensor]) -> Vec<f64> {
    tensors
        .iter()
        .flat_map(|t| Vec::<f64>::try_from(t.flatten(0, -1)).expect("f64 tensor"))
        .collect()
}

/// Central differences of eq. 15 with respect to every scalar of `w0`.
fn finite_difference(
    c: &MamlConfig,
    w0: &[Tensor],
    target: &[Tensor],
    tasks: &[TaskShots],
) -> Vec<f64> {
    central_differences(w0, |moved| {
        meta_loss(c, moved, StepSize::Shared, target, tasks)
    })
}

/// Central differences of `f` with respect to every scalar of `params`.
fn central_differences(params: &[Tensor], f: impl Fn(&[Tensor]) -> f64) -> Vec<f64> {
    let eps = 1e-6;
    let mut grad = Vec::new();
    for (p, w) in params.iter().enumerate() {
        for j in 0..w.numel() as i64 {
            let at = |delta: f64| {
                let moved = fresh_leaves(params);
                let _ = moved[p].view(-1).get(j).detach().g_add_scalar_(delta);
                f(&moved)
            };
            grad.push((at(eps) - at(-eps)) / (2.0 * eps));
        }
    }
    grad
}

fn norm(v: &[f64]) -> f64 {
    v.iter().map(|x| x * x).sum::<f64>().sqrt()
}

fn relative_error(a: &[f64], b: &[f64]) -> f64 {
    let diff: Vec<f64> = a.iter().zip(b).map(|(x, y)| x - y).collect();
    norm(&diff) / norm(a).max(norm(b))
}

#[test]
fn second_order_meta_gradient_matches_finite_differences() {
    single_threaded();
    let mut rng = ChaCha8Rng::seed_from_u64(1);
    let tasks = shots(3, 16, Kind::Double, &mut rng);
    let w0 = leaves(2);
    let target = leaves(3);
    for inner_loss in [Algo::CQL, Algo::DQN] {
        for inner_steps in [1, 3] {
            let c = config(inner_loss, inner_steps, false);
            let analytic = meta_gradient(&c, &w0, &target, &tasks);
            let numeric = finite_difference(&c, &w0, &target, &tasks);
            let error = relative_error(&analytic, &numeric);
            println!("{inner_loss:?}, {inner_steps} inner steps: relative error {error:.3e}, |grad| {:.3e}", norm(&numeric));
            assert!(
                error < 1e-3,
                "{inner_loss:?}, {inner_steps} inner steps: relative error {error:e}"
            );
        }
    }
}

#[test]
fn meta_sgd_gradients_of_w0_and_step_sizes_match_finite_differences() {
    single_threaded();
    let mut rng = ChaCha8Rng::seed_from_u64(30);
    let tasks = shots(3, 16, Kind::Double, &mut rng);
    let w0 = leaves(31);
    let target = leaves(32);
    // A different step size for every weight, 0.1 to about 0.5.
    let lr: Vec<Tensor> = leaves(33).iter().map(|w| w.abs() * 0.5 + 0.1).collect();
    for inner_loss in [Algo::CQL, Algo::DQN] {
        let c = config(inner_loss, 2, false);
        let (w0_leaves, lr_leaves) = (fresh_leaves(&w0), fresh_leaves(&lr));
        c.backward_meta_loss(&w0_leaves, StepSize::PerWeight(&lr_leaves), &target, &tasks);
        let grads =
            |leaves: &[Tensor]| flatten(&leaves.iter().map(Tensor::grad).collect::<Vec<_>>());
        let numeric_w0 = central_differences(&w0, |moved| {
            meta_loss(&c, moved, StepSize::PerWeight(&lr), &target, &tasks)
        });
        let numeric_lr = central_differences(&lr, |moved| {
            meta_loss(&c, &w0, StepSize::PerWeight(moved), &target, &tasks)
        });
        for (what, analytic, numeric) in [
            ("w0", grads(&w0_leaves), numeric_w0),
            ("step sizes", grads(&lr_leaves), numeric_lr),
        ] {
            let error = relative_error(&analytic, &numeric);
            assert!(
                error < 1e-3 && norm(&numeric) > 1e-3,
                "{inner_loss:?}, gradient of the {what}: relative error {error:e}, |grad| {:e}",
                norm(&numeric)
            );
        }
    }
    // Step sizes all equal to eta_inner are MAML's shared step.
    let c = config(Algo::CQL, 2, false);
    let shared: Vec<Tensor> = w0.iter().map(|w| w.full_like(c.meta.eta_inner)).collect();
    let maml = meta_loss(&c, &w0, StepSize::Shared, &target, &tasks);
    let meta_sgd = meta_loss(&c, &w0, StepSize::PerWeight(&shared), &target, &tasks);
    assert!((maml - meta_sgd).abs() < 1e-12, "{maml} != {meta_sgd}");
}

/// `meta.w0_loss_weight` = beta adds `beta * sum_i L(w0; query_i)` to eq. 15: the gradient is
/// that sum's derivative, checked by central differences, and beta = 0 is eq. 15 to the bit.
#[test]
fn the_w0_loss_term_adds_its_own_gradient_to_eq15s() {
    single_threaded();
    let mut rng = ChaCha8Rng::seed_from_u64(40);
    let tasks = shots(3, 16, Kind::Double, &mut rng);
    let (w0, target) = (leaves(41), leaves(42));
    let plain = config(Algo::CQL, 2, false);
    let mut with_term = plain.clone();
    with_term.meta.w0_loss_weight = 0.7;
    let analytic = meta_gradient(&with_term, &w0, &target, &tasks);
    let numeric = central_differences(&w0, |moved| {
        let w0_loss: f64 = tasks
            .iter()
            .map(|t| plain.task_loss(moved, &target, &t.query).double_value(&[]))
            .sum();
        meta_loss(&plain, moved, StepSize::Shared, &target, &tasks) + 0.7 * w0_loss
    });
    let error = relative_error(&analytic, &numeric);
    assert!(error < 1e-3, "relative error {error:e}");
    // The term moves the gradient: it is not eq. 15's alone.
    let eq15 = meta_gradient(&plain, &w0, &target, &tasks);
    assert!(
        relative_error(&analytic, &eq15) > 1e-2,
        "the w0 term changed nothing"
    );
    with_term.meta.w0_loss_weight = 0.0;
    assert_eq!(meta_gradient(&with_term, &w0, &target, &tasks), eq15);
}

#[test]
fn tasks_stacked_with_padding_give_each_task_its_own_meta_gradient() {
    single_threaded();
    // Tasks of 16, 11 and 5 rows: the stacked computation pads the shorter two with rows of
    // weight 0; each task alone needs no padding. The sum of the lone gradients is the truth.
    let mut rng = ChaCha8Rng::seed_from_u64(10);
    let tasks: Vec<TaskShots> = [16, 11, 5]
        .into_iter()
        .enumerate()
        .map(|(i, rows)| TaskShots {
            support: batch(rows, i as f64, Kind::Double, &mut rng),
            query: batch(rows + 2, i as f64, Kind::Double, &mut rng),
        })
        .collect();
    let w0 = leaves(11);
    let target = leaves(12);
    for inner_loss in [Algo::CQL, Algo::DQN] {
        for first_order in [false, true] {
            let c = config(inner_loss, 2, first_order);
            let stacked = meta_gradient(&c, &w0, &target, &tasks);
            let mut alone = vec![0.0; stacked.len()];
            for task in tasks.chunks(1) {
                for (a, g) in alone.iter_mut().zip(meta_gradient(&c, &w0, &target, task)) {
                    *a += g;
                }
            }
            let error = relative_error(&stacked, &alone);
            assert!(
                error < 1e-10,
                "{inner_loss:?}, first order {first_order}: stacked and per-task meta-gradients differ by {error:e}"
            );
        }
    }
}

#[test]
fn first_order_gradient_is_the_query_gradient_at_the_adapted_weights() {
    single_threaded();
    let mut rng = ChaCha8Rng::seed_from_u64(4);
    let tasks = shots(2, 16, Kind::Double, &mut rng);
    let w0 = leaves(5);
    let target = leaves(6);
    for inner_steps in [1, 3] {
        let first = config(Algo::CQL, inner_steps, true);
        // sum_i grad_w L(w; query_i) evaluated at w = w_i, with w_i taken as a constant point.
        let mut expected = vec![0.0; flatten(&w0).len()];
        for task in &tasks {
            let w_i: Vec<Tensor> = first
                .adapt(&w0, StepSize::Shared, &target, &task.support)
                .iter()
                .map(|w| w.detach().set_requires_grad(true))
                .collect();
            let loss = first.task_loss(&w_i, &target, &task.query);
            let grads = Tensor::run_backward(&[&loss], &w_i, false, false);
            for (e, g) in expected.iter_mut().zip(flatten(&grads)) {
                *e += g;
            }
        }
        let fo = meta_gradient(&first, &w0, &target, &tasks);
        let error = relative_error(&fo, &expected);
        assert!(
            error < 1e-12,
            "{inner_steps} inner steps: first order is not the query gradient at w_i ({error:e})"
        );

        // It is not the true meta-gradient: that one carries the curvature of the inner loss.
        let second = meta_gradient(&config(Algo::CQL, inner_steps, false), &w0, &target, &tasks);
        let gap = relative_error(&fo, &second);
        println!("{inner_steps} inner steps: first vs second order relative difference {gap:.3e}");
        assert!(
            gap > 1e-2,
            "{inner_steps} inner steps: first and second order agree to {gap:e}"
        );
    }
}

#[test]
fn one_step_second_order_term_is_the_inner_hessian_times_the_query_gradient() {
    single_threaded();
    // For one inner step, d w1 / d w0 = I - eta H_s(w0), so
    // second order - first order = -eta H_s(w0) grad L_q(w1), per task. H_s v comes from central
    // differences of the support gradient along v, independently of the code under test.
    let mut rng = ChaCha8Rng::seed_from_u64(7);
    let tasks = shots(1, 16, Kind::Double, &mut rng);
    let w0 = leaves(8);
    let target = leaves(9);
    let first = config(Algo::CQL, 1, true);
    let fo = meta_gradient(&first, &w0, &target, &tasks);
    let so = meta_gradient(&config(Algo::CQL, 1, false), &w0, &target, &tasks);
    let support_gradient = |w: &[Tensor]| {
        let loss = first.task_loss(w, &target, &tasks[0].support);
        Tensor::run_backward(&[&loss], w, false, false)
    };
    let eps = 1e-6;
    let along = |sign: f64| -> Vec<f64> {
        let mut offset = 0;
        let moved: Vec<Tensor> = w0
            .iter()
            .map(|w| {
                let n = w.numel();
                let v = Tensor::from_slice(&fo[offset..offset + n]).view(w.size().as_slice());
                offset += n;
                (w.detach() + v * (sign * eps)).set_requires_grad(true)
            })
            .collect();
        flatten(&support_gradient(&moved))
    };
    let (plus, minus) = (along(1.0), along(-1.0));
    let expected: Vec<f64> = plus
        .iter()
        .zip(&minus)
        .map(|(p, m)| -first.meta.eta_inner * (p - m) / (2.0 * eps))
        .collect();
    let difference: Vec<f64> = so.iter().zip(&fo).map(|(s, f)| s - f).collect();
    let error = relative_error(&difference, &expected);
    println!(
        "second - first order vs -eta H v: relative error {error:.3e}, |difference| {:.3e}",
        norm(&difference)
    );
    assert!(
        norm(&difference) > 1e-3 * norm(&fo),
        "the curvature term vanished"
    );
    assert!(
        error < 1e-4,
        "second - first order is not -eta H v: relative error {error:e}"
    );
}

#[test]
fn meta_training_lowers_the_meta_loss_on_held_out_query_data() {
    single_threaded();
    let mut rng = ChaCha8Rng::seed_from_u64(10);
    let tasks: Vec<MetaTask> = (0..4)
        .map(|i| MetaTask {
            name: format!("task-{i}"),
            support: batch(128, i as f64, Kind::Float, &mut rng),
            query: batch(128, i as f64, Kind::Float, &mut rng),
        })
        .collect();
    // Fresh transitions of the same tasks that meta-training never sees.
    let held_out = shots(4, 128, Kind::Float, &mut ChaCha8Rng::seed_from_u64(11));
    for first_order in [false, true] {
        let mut c = config(Algo::CQL, 1, first_order);
        c.meta.eta_inner = 0.05;
        c.meta.eta_outer = 3e-3;
        // Qhat stays the initial w0, so before and after are the same objective.
        c.meta.target_update_meta_epochs = 1000;
        let mut maml = Maml::new(QNetworkConfig::new(OBS, ACTIONS, &[32, 32]).init(12), c, 13)
            .expect("optimiser");
        let before = maml.meta_loss(&held_out);
        for _ in 0..200 {
            maml.meta_epoch(&tasks).expect("tasks");
        }
        let after = maml.meta_loss(&held_out);
        println!("first_order = {first_order}: held-out meta-loss {before:.4} -> {after:.4}");
        assert!(
            after < 0.6 * before,
            "first_order = {first_order}: held-out meta-loss {before} -> {after}"
        );
    }
}

/// `meta.huber` puts the Huber TD form into MAML's losses, as `learner.huber` does, without
/// turning it on for fine-tuning.
#[test]
fn meta_huber_gives_mamls_losses_the_huber_td_form() {
    single_threaded();
    let set =
        |key: &str| Config::from_toml_str("", "--set", &[format!("{key}=true")]).expect("config");
    let (meta_set, learner_set) = (set("meta.huber"), set("learner.huber"));
    assert!(
        !meta_set.learner.huber,
        "meta.huber must leave learner.huber off"
    );
    let w = QNetworkConfig::new(OBS, ACTIONS, &[6]).init(3).parameters();
    let shots = batch(32, 2.0, Kind::Float, &mut ChaCha8Rng::seed_from_u64(4));
    let loss = |c: &Config| {
        let maml = MamlConfig::from_config(c);
        maml.task_loss(&w, &w, &shots).double_value(&[])
    };
    let (meta, learner, eq7) = (
        loss(&meta_set),
        loss(&learner_set),
        loss(&Config::default()),
    );
    assert_eq!(
        meta, learner,
        "meta.huber and learner.huber give MAML different losses"
    );
    assert!(
        (meta - eq7).abs() > 1e-3 * eq7.abs(),
        "the Huber loss {meta} equals the squared one {eq7}"
    );
}

/// w0's weights, exactly (f32 widens to f64 without rounding).
fn weights(maml: &Maml) -> Vec<f64> {
    let params: Vec<Tensor> = maml
        .w0()
        .parameters()
        .iter()
        .map(|p| p.to_kind(Kind::Double))
        .collect();
    flatten(&params)
}

#[test]
fn an_interrupted_and_resumed_meta_training_ends_at_the_uninterrupted_w0() {
    single_threaded();
    for (learn_inner_lr, average) in [(false, 0.0), (true, 0.0), (false, 0.9)] {
        resumed_ends_where_uninterrupted_ends(learn_inner_lr, average);
    }
}

/// With Meta-SGD the learned step sizes and their Adam moments are part of the saved state;
/// with averaging, the checkpoint holds the average and the state the iterate.
fn resumed_ends_where_uninterrupted_ends(learn_inner_lr: bool, average: f64) {
    let mut rng = ChaCha8Rng::seed_from_u64(20);
    let tasks: Vec<MetaTask> = (0..3)
        .map(|i| MetaTask {
            name: format!("task-{i}"),
            support: batch(64, i as f64, Kind::Float, &mut rng),
            query: batch(64, i as f64, Kind::Float, &mut rng),
        })
        .collect();
    let mut c = config(Algo::CQL, 2, false);
    c.meta.eta_inner = 0.05;
    c.meta.eta_outer = 3e-3;
    // The target network (refreshed at epochs 0, 4, 8) and the task sampling (2 of 3 tasks) both
    // carry state across the interruption after epoch 6, besides Adam's moments.
    c.meta.target_update_meta_epochs = 4;
    c.meta.tasks_per_meta_epoch = 2;
    c.meta.learn_inner_lr = learn_inner_lr;
    c.meta.average_decay_per_outer_step = average;
    let hidden = [16];
    let network = || QNetworkConfig::new(OBS, ACTIONS, &hidden).init(21);
    let (seed, epochs, interrupted_at) = (22, 10, 6);

    let mut straight = Maml::new(network(), c.clone(), seed).expect("maml");
    for _ in 0..epochs {
        straight.meta_epoch(&tasks).expect("tasks");
    }

    let mut config = uavmeta_proto::config::Config::default();
    config.world.devices = 1; // 2 + K = OBS inputs, 5K = ACTIONS outputs
    config.learner.hidden = hidden.to_vec();
    let dir = tempfile::tempdir().expect("temp dir");
    let path = dir.path().join("epoch-00006");
    let mut first = Maml::new(network(), c.clone(), seed).expect("maml");
    for _ in 0..interrupted_at {
        first.meta_epoch(&tasks).expect("tasks");
    }
    first.save_state(&path).expect("save the state");
    checkpoint::save(&path, first.w0(), "cql-maml", interrupted_at, &config).expect("save w0");
    drop(first);

    let (w0, _) = checkpoint::load(&path, &config).expect("load w0");
    let mut resumed = Maml::resume(w0, c.clone(), &path).expect("resume");
    assert_eq!(resumed.epochs_done(), interrupted_at);
    for _ in interrupted_at..epochs {
        resumed.meta_epoch(&tasks).expect("tasks");
    }
    assert_eq!(
        weights(&resumed),
        weights(&straight),
        "resumed != uninterrupted (learn_inner_lr {learn_inner_lr}, average {average})"
    );

    // The same w0 without its state (fresh moments, target and sampling) ends elsewhere: the
    // comparison above can fail.
    let (w0, _) = checkpoint::load(&path, &config).expect("load w0");
    let mut restarted = Maml::new(w0, c, seed).expect("maml");
    for _ in interrupted_at..epochs {
        restarted.meta_epoch(&tasks).expect("tasks");
    }
    assert_ne!(weights(&restarted), weights(&straight));
}

#[test]
fn a_corrupt_training_state_is_refused_naming_the_file() {
    let dir = tempfile::tempdir().expect("temp dir");
    let path = dir.path().join("epoch-00001");
    let c = config(Algo::CQL, 1, true);
    let maml = Maml::new(
        QNetworkConfig::new(OBS, ACTIONS, &[4]).init(1),
        c.clone(),
        2,
    )
    .expect("maml");
    maml.save_state(&path).expect("save the state");
    let tensors = checkpoint::state_paths(&path).0;
    let mut bytes = std::fs::read(&tensors).expect("read");
    let last = bytes.len() - 1;
    bytes[last] ^= 0xff;
    std::fs::write(&tensors, bytes).expect("write");
    let err = Maml::resume(QNetworkConfig::new(OBS, ACTIONS, &[4]).init(1), c, &path)
        .err()
        .expect("a corrupt state must be refused")
        .to_string();
    assert!(
        err.contains("corrupt") && err.contains("state.safetensors"),
        "{err}"
    );
}

/// With `meta.average_decay_per_outer_step` = d the published init is the moving average of the iterates, which
/// averaging leaves as they are: after two outer steps from w_0, d^2 w_0 + d (1 - d) w_1 +
/// (1 - d) w_2, with w_1 and w_2 the iterates of the same run without averaging.
#[test]
fn averaged_init_is_the_moving_average_of_the_iterates() {
    single_threaded();
    let mut rng = ChaCha8Rng::seed_from_u64(30);
    let tasks: Vec<MetaTask> = (0..2)
        .map(|i| MetaTask {
            name: format!("task-{i}"),
            support: batch(16, i as f64, Kind::Float, &mut rng),
            query: batch(16, i as f64, Kind::Float, &mut rng),
        })
        .collect();
    let network = || QNetworkConfig::new(OBS, ACTIONS, &[8]).init(31);
    let plain = config(Algo::CQL, 1, false);
    let d = 0.5;
    let mut averaged = plain.clone();
    averaged.meta.average_decay_per_outer_step = d;
    let mut last = Maml::new(network(), plain, 32).expect("maml");
    let w_0 = weights(&last);
    last.meta_epoch(&tasks).expect("tasks");
    let w_1 = weights(&last);
    last.meta_epoch(&tasks).expect("tasks");
    let w_2 = weights(&last);
    let mut mean = Maml::new(network(), averaged, 32).expect("maml");
    mean.meta_epoch(&tasks).expect("tasks");
    mean.meta_epoch(&tasks).expect("tasks");
    let expected: Vec<f64> = (0..w_0.len())
        .map(|i| d * d * w_0[i] + d * (1.0 - d) * w_1[i] + (1.0 - d) * w_2[i])
        .collect();
    assert!(relative_error(&weights(&mean), &expected) < 1e-5);
    assert!(
        relative_error(&w_2, &expected) > 1e-3,
        "the iterate is not the average"
    );
}
