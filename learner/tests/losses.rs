//! Eq. 7, eq. 8, behaviour cloning and discrete BCQ against values worked out by hand on a two-row, three-action
//! batch.

use tch::{Kind, Tensor};
use uavmeta_learner::algorithm::{prepare, OfflineAlgorithm, Terms};
use uavmeta_learner::bc::Bc;
use uavmeta_learner::bcq::{supported_values, Bcq};
use uavmeta_learner::cql::{conservative_term, cql_loss};
use uavmeta_learner::dqn::{dqn_loss, Bootstrap, Dqn, TdConfig};
use uavmeta_learner::qnet::QNetworkConfig;
use uavmeta_learner::transitions::{Transitions, TransitionsError};
use uavmeta_proto::config::{LearnerConfig, WorldConfig};
use uavmeta_proto::dataset::Transition;

fn t2(rows: &[[f64; 3]; 2]) -> Tensor {
    Tensor::from_slice(&rows.concat())
        .view([2, 3])
        .to_kind(Kind::Float)
}

/// The batch every hand computation below uses:
/// Q(s, .) = [[1, 2, 3], [0, -1, 4]], a = [2, 0], r = [1, -2],
/// Qhat(s', .) = [[0.5, 2, 1], [3, 0, -1]], gamma = 0.5.
fn fixture() -> (Tensor, Tensor, Transitions) {
    let q = t2(&[[1.0, 2.0, 3.0], [0.0, -1.0, 4.0]]);
    let next = t2(&[[0.5, 2.0, 1.0], [3.0, 0.0, -1.0]]);
    let obs = Tensor::zeros([2, 1], (Kind::Float, tch::Device::Cpu));
    let batch = Transitions {
        obs: obs.shallow_clone(),
        actions: Tensor::from_slice(&[2i64, 0]),
        rewards: Tensor::from_slice(&[1.0f32, -2.0]),
        next_obs: obs,
    };
    (q, next, batch)
}

fn scalar(t: &Tensor) -> f64 {
    t.double_value(&[])
}

#[test]
fn dqn_loss_matches_eq7_by_hand() {
    let (q, next, batch) = fixture();
    // y_0 = 1 + 0.5 * max(0.5, 2, 1) = 2;     Q(s_0, a=2) = 3;  (2 - 3)^2    = 1
    // y_1 = -2 + 0.5 * max(3, 0, -1) = -0.5;  Q(s_1, a=0) = 0;  (-0.5 - 0)^2 = 0.25
    // mean = 1.25 / 2 = 0.625
    let loss = dqn_loss(&q, &next, &batch, 0.5);
    assert_eq!(loss.size(), Vec::<i64>::new());
    assert!((scalar(&loss) - 0.625).abs() < 1e-6, "{}", scalar(&loss));
}

#[test]
fn dqn_options_huber_and_double() {
    let (q, next, batch) = fixture();
    // Huber (delta 1) of the same errors -1 and -0.5: 0.5 * 1 and 0.5 * 0.25; mean 0.3125.
    let huber = TdConfig {
        gamma: 0.5,
        bootstrap: Bootstrap::Max,
        huber: true,
    };
    // Eq. 7's errors with `td`'s options, the online network's outputs `online` at s', averaged.
    let mean_td = |td: TdConfig, online: Option<&Tensor>| {
        let online = |_: &Tensor| {
            online
                .expect("only double DQN reads the online network")
                .shallow_clone()
        };
        let learner = LearnerConfig::default();
        let target = |_: &Tensor| next.shallow_clone();
        scalar(
            &td.td_errors((&Dqn, &learner), &q, &batch, target, online)
                .mean(None),
        )
    };
    let loss = mean_td(huber, None);
    assert!((loss - 0.3125).abs() < 1e-6, "{loss}");

    // Double DQN: the online net picks a* = argmax [[0, 0, 5], [1, 2, 0]] = [2, 1], the target
    // net values them: Qhat(s'_0, 2) = 1, Qhat(s'_1, 1) = 0.
    // y = [1 + 0.5 * 1, -2 + 0.5 * 0] = [1.5, -2]; errors (1.5 - 3)^2 = 2.25, (-2 - 0)^2 = 4; mean
    // 3.125.
    let online = t2(&[[0.0, 0.0, 5.0], [1.0, 2.0, 0.0]]);
    let double = TdConfig {
        gamma: 0.5,
        bootstrap: Bootstrap::Double,
        huber: false,
    };
    let loss = mean_td(double, Some(&online));
    assert!((loss - 3.125).abs() < 1e-6, "{loss}");

    // With both options off, the mean of the TD errors is eq. 7.
    let loss = mean_td(TdConfig::eq7(0.5), None);
    assert!((loss - 0.625).abs() < 1e-6, "{loss}");
}

#[test]
fn cql_loss_matches_eq8_by_hand() {
    let (q, next, batch) = fixture();
    // Row 0: logsumexp(1, 2, 3) = 3 + ln(1 + e^-1 + e^-2), minus Q(s_0, 2) = 3.
    let row0 = 3.0 + (1.0 + (-1.0f64).exp() + (-2.0f64).exp()).ln() - 3.0;
    // Row 1: logsumexp(0, -1, 4) = 4 + ln(e^-4 + e^-5 + 1), minus Q(s_1, 0) = 0.
    let row1 = 4.0 + ((-4.0f64).exp() + (-5.0f64).exp() + 1.0).ln() - 0.0;
    let conservative = (row0 + row1) / 2.0; // = (0.407606 + 4.024745) / 2 = 2.216176
    assert!((conservative - 2.216176).abs() < 1e-6);
    // total = 0.5 * 0.625 + alpha * conservative, alpha = 2: 0.3125 + 4.432351 = 4.744851
    let total = cql_loss(&q, &next, &batch, 0.5, 2.0);
    assert!((scalar(&dqn_loss(&q, &next, &batch, 0.5)) - 0.625).abs() < 1e-6);
    let got = scalar(&conservative_term(&q, &batch));
    assert!((got - conservative).abs() < 1e-5, "{got}");
    let got = scalar(&total);
    assert!((got - (0.3125 + 2.0 * conservative)).abs() < 1e-5, "{got}");
    assert!((got - 4.744851).abs() < 1e-5);
}

#[test]
fn conservative_gradient_is_softmax_minus_onehot() {
    let (q, _, batch) = fixture();
    let q = q.set_requires_grad(true);
    conservative_term(&q, &batch).backward();
    let grad = q.grad();
    // d/dQ(s_i, .) of (1/B) sum_i [logsumexp Q(s_i, .) - Q(s_i, a_i)] = (softmax(Q(s_i, .)) -
    // onehot(a_i)) / B.
    let rows = [[1.0f64, 2.0, 3.0], [0.0, -1.0, 4.0]];
    let actions = [2usize, 0];
    for (i, (row, &a)) in rows.iter().zip(&actions).enumerate() {
        let z: f64 = row.iter().map(|v| v.exp()).sum();
        for (j, v) in row.iter().enumerate() {
            let expected = (v.exp() / z - if j == a { 1.0 } else { 0.0 }) / 2.0;
            let got = grad.double_value(&[i as i64, j as i64]);
            assert!(
                (got - expected).abs() < 1e-6,
                "grad[{i}][{j}] = {got}, expected {expected}"
            );
        }
    }
}

#[test]
fn no_gradient_flows_into_the_target() {
    let (q, next, batch) = fixture();
    let q = q.set_requires_grad(true);
    let next = next.set_requires_grad(true);
    cql_loss(&q, &next, &batch, 0.5, 1.0).backward();
    assert!(!next.grad().defined() || next.grad().abs().sum(Kind::Float).double_value(&[]) == 0.0);
    // dL_td/dQ(s_0, 2) = 2 * (Q - y) / B = 2 * (3 - 2) / 2 = 1, times 0.5 in eq. 8;
    // plus the conservative part (softmax(1,2,3)[2] - 1) / 2.
    let z: f64 = [1.0f64, 2.0, 3.0].iter().map(|v| v.exp()).sum();
    let expected = 0.5 * 1.0 + (3.0f64.exp() / z - 1.0) / 2.0;
    assert!((q.grad().double_value(&[0, 2]) - expected).abs() < 1e-6);
}

fn world_k2() -> WorldConfig {
    WorldConfig {
        devices: 2,
        ..WorldConfig::default()
    }
}

fn transition(
    obs: Vec<u16>,
    action: u16,
    reward: f32,
    next_obs: Vec<u16>,
    truncated: bool,
) -> Transition {
    Transition {
        task: 0,
        actor: 0,
        episode: 3,
        step: 99,
        seq: 7,
        obs,
        action,
        reward,
        next_obs,
        truncated,
    }
}

#[test]
fn batch_normalises_and_scales() {
    // L = 10, aoi_max = 100: x/9, y/9, A/100.
    let t = transition(vec![9, 0, 50, 100], 7, -120.0, vec![3, 6, 1, 2], false);
    let b = Transitions::new(&[t], &world_k2(), 0.01).unwrap();
    let obs: Vec<f32> = b.obs.view([-1]).try_into().unwrap();
    assert_eq!(obs, vec![1.0, 0.0, 0.5, 1.0]);
    let next: Vec<f32> = b.next_obs.view([-1]).try_into().unwrap();
    assert_eq!(next, vec![3.0 / 9.0, 6.0 / 9.0, 0.01, 0.02]);
    assert_eq!(b.actions.int64_value(&[0]), 7);
    assert!((b.rewards.double_value(&[0]) + 1.2).abs() < 1e-6);
}

#[test]
fn truncation_still_bootstraps() {
    // The same transition marked as the episode's last (a time limit) must give the same loss:
    // y = r + gamma * max Qhat(s', .) in both cases, never y = r.
    let world = world_k2();
    let make = |truncated| {
        Transitions::new(
            &[transition(
                vec![1, 1, 1, 1],
                0,
                -10.0,
                vec![1, 2, 2, 1],
                truncated,
            )],
            &world,
            1.0,
        )
        .unwrap()
    };
    let q = Tensor::zeros([1, 10], (Kind::Float, tch::Device::Cpu));
    let next = Tensor::full([1, 10], -5.0, (Kind::Float, tch::Device::Cpu));
    let last = scalar(&dqn_loss(&q, &next, &make(true), 0.9));
    let middle = scalar(&dqn_loss(&q, &next, &make(false), 0.9));
    // y = -10 + 0.9 * -5 = -14.5; (y - 0)^2 = 210.25
    assert!((last - 210.25).abs() < 1e-3, "{last}");
    assert_eq!(last, middle);
}

#[test]
fn batch_rejects_transitions_of_another_world() {
    let short = transition(vec![1, 1, 1], 0, -1.0, vec![1, 1, 1, 1], false);
    match Transitions::new(&[short], &world_k2(), 1.0) {
        Err(
            e @ TransitionsError::ObservationLength {
                got: 3,
                expected: 4,
                ..
            },
        ) => {
            assert!(e.to_string().contains("episode 3, step 99"), "{e}")
        }
        other => panic!(
            "expected an observation length error, got {:?}",
            other.err()
        ),
    }
    let bad_action = transition(vec![1, 1, 1, 1], 10, -1.0, vec![1, 1, 1, 1], false);
    assert!(matches!(
        Transitions::new(&[bad_action], &world_k2(), 1.0),
        Err(TransitionsError::Action {
            action: 10,
            actions: 10,
            ..
        })
    ));
    assert!(matches!(
        Transitions::new::<Transition>(&[], &world_k2(), 1.0),
        Err(TransitionsError::Empty)
    ));
}

#[test]
fn bc_loss_matches_d3rlpy_s_discrete_bc_by_hand() {
    let (q, _, batch) = fixture();
    // Cross-entropy of the logged actions: the conservative rows above, mean 2.216176.
    // d3rlpy's penalty: beta * the mean of the squared log-probabilities (log_softmax of each
    // row: the row less its log-sum-exp, 3.407606 and 4.024744).
    let log_probs = [
        [1.0, 2.0, 3.0].map(|f: f64| f - 3.407606),
        [0.0, -1.0, 4.0].map(|f: f64| f - 4.024744),
    ];
    let penalty = log_probs.iter().flatten().map(|l| l * l).sum::<f64>() / 6.0;
    let expected = 2.216176 + 0.5 * penalty;
    let mean = |rows: Tensor| rows.mean(None);
    let td = Tensor::from(0.0f32);
    let terms = Terms {
        q: &q,
        batch: &batch,
        td: &td,
        mean: &mean,
        alpha: 1.0,
        learner: &LearnerConfig::default(),
    };
    let got = scalar(&Bc.loss(&terms));
    assert!((got - expected).abs() < 1e-5, "{got} against {expected}");
    assert!(!Bc.learns_values());
}

/// Outputs [2, 6] of a BCQ network: the fixture's Q-values, then imitation logits under which
/// row 0 supports actions 1 and 2 only (action 0's probability is e^-2 = 0.14 of the best's,
/// below tau = 0.3) and row 1 supports only action 1.
fn bcq_outputs(q: &Tensor) -> Tensor {
    let logits = t2(&[[0.0, 2.0, 2.0], [0.0, 3.0, 1.0]]);
    Tensor::cat(&[q.shallow_clone(), logits], 1)
}

#[test]
fn bcq_acts_only_on_actions_the_data_supports() {
    let (q, _, _) = fixture();
    let out = bcq_outputs(&q);
    let acting = Bcq
        .acting(&LearnerConfig::default())
        .expect("BCQ acts by its own rule");
    // Row 0: Q = [1, 2, 3] over the supported {1, 2} -> 2. Row 1: Q = [0, -1, 4], but only
    // action 1 is supported (e^-2 < 0.3 for action 2, e^-3 for action 0) -> 1, against Q's 2.
    let greedy: Vec<i64> = acting(&out).argmax(-1, false).try_into().unwrap();
    assert_eq!(greedy, [2, 1]);
    // tau = 0 supports every action: plain argmax Q. tau = 1 keeps the imitation's best.
    let all = LearnerConfig {
        bcq_threshold: 0.0,
        ..LearnerConfig::default()
    };
    let greedy: Vec<i64> = supported_values(&out, all.bcq_threshold)
        .argmax(-1, false)
        .try_into()
        .unwrap();
    assert_eq!(greedy, [2, 2]);
    let unsupported = supported_values(&out, 0.3);
    assert_eq!(scalar(&unsupported.get(0).get(0)), 0.0);
    assert_eq!(scalar(&unsupported.get(1).get(2)), 0.0);
    // Through a network: two heads, and greedy() follows the rule once prepared for BCQ.
    let mut net = QNetworkConfig::new(1, 3, &[2]).init(0);
    prepare(&mut net, "bcq".parse().unwrap(), &LearnerConfig::default());
    assert_eq!(net.config().heads, 2);
    tch::no_grad(|| {
        let mut params = net.parameters();
        params.iter_mut().for_each(|p| {
            let _ = p.zero_();
        });
        let bias = Tensor::from_slice(&[0.0f32, -1.0, 4.0, 0.0, 3.0, 1.0]);
        params.last_mut().unwrap().copy_(&bias);
    });
    let obs = Tensor::zeros([1, 1], (Kind::Float, tch::Device::Cpu));
    assert_eq!(net.greedy(&obs).int64_value(&[0]), 1);
}

#[test]
fn bcq_bootstraps_from_the_online_network_s_best_supported_action_and_clones_the_data() {
    let (q, next, batch) = fixture();
    let learner = LearnerConfig::default();
    // The online network's outputs at s' are bcq_outputs(q): supported best actions [2, 1];
    // the target network values them: Qhat(s'_0, 2) = 1, Qhat(s'_1, 1) = 0.
    let next_target = Tensor::cat(&[next.shallow_clone(), next.zeros_like()], 1);
    let online = bcq_outputs(&q);
    let v = Bcq.next_value(&TdConfig::eq7(0.5), &learner, &next_target, &|| {
        online.shallow_clone()
    });
    let v: Vec<f32> = v.try_into().unwrap();
    assert_eq!(v, [1.0, 0.0]);
    // The loss: eq. 7 with those values, y = [1 + 0.5, -2 + 0] against Q(s, a) = [3, 0]:
    // (1.5 - 3)^2 = 2.25 and 4, mean 3.125; plus BC's loss on the imitation logits.
    let out = bcq_outputs(&q);
    let td = TdConfig::eq7(0.5)
        .td_errors(
            (&Bcq, &learner),
            &out,
            &batch,
            |_| next_target.shallow_clone(),
            |_| online.shallow_clone(),
        )
        .mean(None);
    assert!((scalar(&td) - 3.125).abs() < 1e-6, "{}", scalar(&td));
    let logits = out.narrow(1, 3, 3);
    let mean = |rows: Tensor| rows.mean(None);
    let mut terms = Terms {
        q: &logits,
        batch: &batch,
        td: &td,
        mean: &mean,
        alpha: 1.0,
        learner: &learner,
    };
    let imitation = Bc.loss(&terms);
    terms.q = &out;
    let got = scalar(&Bcq.loss(&terms));
    assert!((got - 3.125 - scalar(&imitation)).abs() < 1e-5, "{got}");
}
