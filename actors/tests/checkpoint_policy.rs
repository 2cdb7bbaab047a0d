//! `q:P:CHECKPOINT`: a saved Q-network's greedy policy, with a uniform random action with
//! probability P, as a behaviour policy (`uavmeta_actors::policy::build`).

use std::path::{Path, PathBuf};

use indicatif::ProgressBar;
use uavmeta_actors::collect::collect;
use uavmeta_actors::policy::q_policy::QPolicy;
use uavmeta_actors::policy::{self};
use uavmeta_learner::checkpoint;
use uavmeta_learner::qnet::{QNetwork, QNetworkConfig};
use uavmeta_proto::config::{Config, TaskConfig};
use uavmeta_proto::dataset::DatasetReader;
use uavmeta_world::heuristics::{PolicySpec, RandomPolicy};
use uavmeta_world::rollout::Policy;
use uavmeta_world::world::World;

/// A network of `config`'s learner shape, seeded 3, saved as `dir/net`.
fn saved_network(config: &Config, dir: &Path) -> (QNetwork, PathBuf) {
    let q = QNetworkConfig::for_world(&config.world, &config.learner.hidden).init(3);
    let path = dir.join("net");
    checkpoint::save(&path, &q, "cql", 1, config).expect("save the network");
    (q, path)
}

/// The actions `policy` takes over one episode, and the greedy actions of `q` in the same states.
fn episode(config: &Config, policy: &mut dyn Policy, q: &QNetwork) -> (Vec<usize>, Vec<usize>) {
    let mut world = World::new(&config.world, &TaskConfig::one_off(300.0, None), 4);
    world.reset();
    let mut greedy = QPolicy::new(q);
    let (mut taken, mut best) = (Vec::new(), Vec::new());
    for _ in 0..config.world.horizon {
        best.push(greedy.act(&world));
        let action = policy.act(&world);
        taken.push(action);
        world.step(action);
    }
    (taken, best)
}

#[test]
fn a_checkpoint_policy_is_its_networks_greedy_policy_mixed_with_uniform_actions() {
    let config = Config::default();
    let dir = tempfile::tempdir().unwrap();
    let (q, path) = saved_network(&config, dir.path());
    let spec = |epsilon| PolicySpec::Checkpoint {
        epsilon,
        path: path.clone(),
    };

    // P = 0: the loaded network acts as the saved one does, in every state of the episode.
    let mut greedy = policy::build(&spec(0.0), &config, 9, None).unwrap();
    let (taken, best) = episode(&config, greedy.as_mut(), &q);
    assert_eq!(taken, best);

    // P = 1: the uniform stream of the same seed, untouched by the coin.
    let mut uniform = policy::build(&spec(1.0), &config, 9, None).unwrap();
    let (taken, _) = episode(&config, uniform.as_mut(), &q);
    let mut random = RandomPolicy::new(9);
    let world = World::new(&config.world, &TaskConfig::one_off(300.0, None), 4);
    let expected: Vec<usize> = taken.iter().map(|_| random.act(&world)).collect();
    assert_eq!(taken, expected);

    // P = 0.3: about a third of the steps leave the greedy action, the same ones for the same seed.
    let mut mixed = policy::build(&spec(0.3), &config, 9, None).unwrap();
    let (taken, best) = episode(&config, mixed.as_mut(), &q);
    let off = taken.iter().zip(&best).filter(|(a, b)| a != b).count();
    assert!((10..=50).contains(&off), "{off} of 100 steps off greedy");
    let mut again = policy::build(&spec(0.3), &config, 9, None).unwrap();
    assert_eq!(episode(&config, again.as_mut(), &q).0, taken);
}

#[test]
fn checkpoint_specs_parse_and_refuse_what_is_not_one() {
    let parsed: PolicySpec = "q:0.05:runs/a b/online-dqn".parse().unwrap();
    assert_eq!(
        parsed,
        PolicySpec::Checkpoint {
            epsilon: 0.05,
            path: "runs/a b/online-dqn".into()
        }
    );
    assert_eq!(parsed.to_string(), "q:0.05:runs/a b/online-dqn");
    for (text, part) in [
        ("q:runs/net", "expected q:P:CHECKPOINT"),
        ("q:0.1:", "expected q:P:CHECKPOINT"),
        ("q:1.5:runs/net", "`1.5` is not a probability"),
        ("q:-0.5:x", "`-0.5` is not a probability"),
    ] {
        let message = text.parse::<PolicySpec>().unwrap_err().to_string();
        assert!(
            message.contains(text) && message.contains(part),
            "{text}: {message}"
        );
    }
}

#[test]
fn a_checkpoint_that_cannot_serve_is_named_with_the_reason() {
    let config = Config::default();
    let dir = tempfile::tempdir().unwrap();
    let missing = dir.path().join("nothing-here");
    let spec = PolicySpec::Checkpoint {
        epsilon: 0.1,
        path: missing.clone(),
    };
    let message = policy::build(&spec, &config, 0, None)
        .err()
        .unwrap()
        .to_string();
    assert!(
        message.contains(&format!("q:0.1:{}", missing.display()))
            && message.contains("nothing-here.json")
            && message.contains("No such file"),
        "{message}"
    );

    // A network of another world's size: the key that differs is named.
    let (_, path) = saved_network(&config, dir.path());
    let other = Config::from_toml_str("[world]\ndevices = 4", "four.toml", &[]).unwrap();
    let spec = PolicySpec::Checkpoint { epsilon: 0.0, path };
    let message = policy::build(&spec, &other, 0, None)
        .err()
        .unwrap()
        .to_string();
    assert!(message.contains("world.devices"), "{message}");

    // A plain spec's builder refuses it rather than guessing.
    let message = spec.build(&config, 0, None).err().unwrap().to_string();
    assert!(
        message.contains("uavmeta_actors::policy::build"),
        "{message}"
    );
}

/// `collect --policy q:P:FILE` writes the policy's rollout, and the saved config alone makes the
/// same bytes again.
#[test]
fn a_checkpoint_policy_collects_a_reproducible_dataset() {
    let dir = tempfile::tempdir().unwrap();
    let mut config = Config::default();
    let (_, path) = saved_network(&config, dir.path());
    config.collect.policy = format!("q:0.2:{}", path.display());
    config.collect.transitions = 250;
    let (a, b) = (dir.path().join("a.uavds"), dir.path().join("b.uavds"));
    let summary = collect(&config, "lambda-300", &a, &ProgressBar::hidden()).unwrap();
    assert_eq!((summary.transitions, summary.steps), (250, 250));
    let reader = DatasetReader::open(&a).unwrap();
    assert_eq!(reader.transitions().len(), 250);
    let saved = Config::load(&uavmeta_actors::collect::config_path(&a), &[]).unwrap();
    assert_eq!(saved.collect.policy, config.collect.policy);
    collect(&saved, "lambda-300", &b, &ProgressBar::hidden()).unwrap();
    assert_eq!(std::fs::read(&a).unwrap(), std::fs::read(&b).unwrap());
}
