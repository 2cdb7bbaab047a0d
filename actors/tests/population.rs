//! A population of online DQN agents trained as one computation is the agents trained alone:
//! - a population of one is the single agent ([`OnlineDqn`]) bit for bit: the same replay buffer,
//!   the same network, the same selection evaluations;
//! - each member of a population of three (other tasks, other seeds, n-step returns) follows its
//!   separate run up to float rounding over the first few hundred gradient steps: the same
//!   transitions and networks within float tolerance;
//! - members share nothing: a member's run does not depend on who else is in the population.

use tch::Tensor;
use uavmeta_actors::policy::dqn_online::OnlineDqn;
use uavmeta_actors::policy::dqn_population::{DqnPopulation, MemberSpec};
use uavmeta_learner::qnet::QNetwork;
use uavmeta_proto::config::{Config, TaskConfig};
use uavmeta_proto::dataset::Transition;

mod support;

/// configs/default.toml on the small world with short agents whose every rule is due within the
/// run: warm-up, the target refresh, clipping, selection.
fn small_world(extra: &[&str]) -> Config {
    let agent = [
        "collect.dqn_steps=1500",
        "collect.replay_capacity=1000",
        "collect.eps_decay_steps=600",
        "collect.learning_starts=200",
        "collect.dqn_target_update_every=300",
        "collect.dqn_select_every=500",
        "collect.dqn_grad_clip_norm=1",
    ];
    support::small_world(&[&agent[..], extra].concat())
}

fn spec(lambda: f64, task_id: u32, seed: u64) -> MemberSpec {
    MemberSpec {
        task: TaskConfig::one_off(lambda, None),
        task_id,
        actor: 0,
        seed,
    }
}

fn single(config: &Config, m: &MemberSpec) -> OnlineDqn {
    let mut agent = OnlineDqn::new(config, &m.task, m.task_id, m.actor, m.seed);
    agent.train().unwrap();
    agent
}

fn population(config: &Config, members: &[MemberSpec]) -> DqnPopulation {
    let mut p = DqnPopulation::new(config, members, tch::Device::Cpu);
    p.train_steps(config.collect.dqn_steps).unwrap();
    p
}

fn transitions<'a>(it: impl Iterator<Item = &'a Transition>) -> Vec<Transition> {
    it.cloned().collect()
}

fn bit_equal(a: &QNetwork, b: &QNetwork) -> bool {
    a.parameters()
        .iter()
        .zip(b.parameters())
        .all(|(x, y): (&Tensor, Tensor)| x.equal(&y))
}

#[test]
fn a_population_of_one_is_the_single_agent_bit_for_bit() {
    tch::set_num_threads(1);
    let config = small_world(&[]);
    let m = spec(300.0, 0, 11);
    let alone = single(&config, &m);
    let one = population(&config, std::slice::from_ref(&m));
    let state = one.member(0);
    assert!(
        transitions(alone.replay_buffer().iter()) == transitions(state.replay_buffer().iter()),
        "the replay buffers differ"
    );
    assert_eq!(alone.episode_returns(), state.episode_returns());
    assert_eq!(alone.selection_evaluations(), state.selection_evaluations());
    assert!(
        state.selection_evaluations().len() >= 2,
        "selection never ran"
    );
    assert!(
        bit_equal(alone.q_network(), &one.q_network(0)),
        "the kept networks differ by up to {}",
        alone.q_network().max_abs_difference(&one.q_network(0))
    );
    assert!(
        bit_equal(alone.state().best().unwrap(), &one.q_network(0)),
        "the population's member network is not its kept snapshot"
    );
}

#[test]
fn each_member_of_a_population_follows_its_own_separate_run() {
    tch::set_num_threads(1);
    // A few hundred gradient steps, with n-step returns: within them float rounding has not yet
    // flipped a greedy action, so the transitions agree exactly and the weights closely.
    let config = small_world(&["collect.dqn_steps=600", "collect.dqn_n_step=3"]);
    let members = [spec(300.0, 0, 1), spec(1000.0, 1, 2), spec(0.0, 2, 3)];
    let together = population(&config, &members);
    for (i, m) in members.iter().enumerate() {
        let alone = single(&config, m);
        let state = together.member(i);
        assert!(
            transitions(alone.replay_buffer().iter()) == transitions(state.replay_buffer().iter()),
            "member {i}'s transitions differ from its separate run's"
        );
        assert_eq!(
            alone.episode_returns(),
            state.episode_returns(),
            "member {i}"
        );
        let gap = alone.q_network().max_abs_difference(&together.q_network(i));
        eprintln!("member {i}: largest weight difference from its separate run {gap:e}");
        assert!(gap < 1e-4, "member {i} drifted {gap} from its separate run");
    }
    // Without the others, member 1 is the same run: nothing passes between members.
    let pair = population(&config, &members[1..2]);
    let gap = pair.q_network(0).max_abs_difference(&together.q_network(1));
    assert!(gap < 1e-4, "member 1 depends on its neighbours: {gap}");
    assert!(
        transitions(pair.member(0).replay_buffer().iter())
            == transitions(together.member(1).replay_buffer().iter())
    );
}

/// The dataset stage's path: one job collected as a population writes `uavmeta collect`'s files
/// byte for byte; two jobs write two complete datasets, each with its own seed in its config.
#[test]
fn a_population_collects_the_files_collect_writes() {
    use indicatif::ProgressBar;
    use uavmeta_actors::collect::PopulationJob;
    use uavmeta_actors::collect::{agent_path, collect, collect_population, config_path};
    use uavmeta_learner::checkpoint::CheckpointPaths;
    use uavmeta_proto::dataset::DatasetReader;

    tch::set_num_threads(1);
    let dir = tempfile::tempdir().unwrap();
    let config = small_world(&["collect.dqn_steps=800", "collect.transitions=200"]);
    let task = "lambda-300";
    let alone = dir.path().join("alone.uavd");
    collect(&config, task, &alone, &ProgressBar::hidden()).unwrap();
    let one = dir.path().join("one.uavd");
    let job = PopulationJob {
        config: &config,
        task,
        out: &one,
    };
    collect_population(&[job], tch::Device::Cpu, &ProgressBar::hidden()).unwrap();
    let bytes = |p: &std::path::Path| std::fs::read(p).unwrap();
    assert!(bytes(&alone) == bytes(&one), "the datasets differ");
    assert_eq!(bytes(&config_path(&alone)), bytes(&config_path(&one)));
    let weights = |p: &std::path::Path| CheckpointPaths::new(&agent_path(p)).weights;
    assert!(
        bytes(&weights(&alone)) == bytes(&weights(&one)),
        "the agents differ"
    );

    let mut other = config.clone();
    other.collect.seed += 1;
    let outs = [dir.path().join("a.uavd"), dir.path().join("b.uavd")];
    let jobs = [
        PopulationJob {
            config: &config,
            task: "lambda-1000",
            out: &outs[0],
        },
        PopulationJob {
            config: &other,
            task: "lambda-0",
            out: &outs[1],
        },
    ];
    collect_population(&jobs, tch::Device::Cpu, &ProgressBar::hidden()).unwrap();
    for (out, (name, seed)) in outs.iter().zip([("lambda-1000", 0), ("lambda-0", 1)]) {
        let reader = DatasetReader::open(out).unwrap();
        assert_eq!(reader.transitions().len(), 200);
        assert_eq!(reader.header().task_name, name);
        let saved = Config::load(&config_path(out), &[]).unwrap();
        assert_eq!(saved.collect.seed, config.collect.seed + seed);
        assert!(uavmeta_learner::checkpoint::read_meta(&agent_path(out)).is_ok());
    }
}
