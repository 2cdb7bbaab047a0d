//! Hostile input, end to end (issue #31): a publisher written against `uavmeta_proto`'s public
//! API sends what no actor would, and the real store, real actors and the real dataset files
//! must come out of it intact; bad configs and run directories are refused before any process
//! starts. Each test runs in its own iceoryx2 domain, removed at the end.

use std::path::{Path, PathBuf};

use uavmeta_proto::config::{Config, RunConfig};
use uavmeta_proto::dataset::{DatasetHeader, DatasetWriter, Transition};
use uavmeta_proto::metrics::store as names;
use uavmeta_proto::payload::{self, ServiceNames, TransitionSlot};
use uavmeta_runtime::actor::ActorOptions;
use uavmeta_runtime::domain;
use uavmeta_runtime::metrics::{parse, sum, Sample};
use uavmeta_runtime::run_dir::RunDir;
use uavmeta_runtime::transport::{self, TransitionPublisher};
use uavmeta_world::rollout::record_step;
use uavmeta_world::world::World;

mod support;
use support::{config_args, run_dir, wait_until, within, Proc};

/// A run directory in an iceoryx2 domain of its own, whose files go when it is dropped.
struct Run {
    dir: tempfile::TempDir,
    domain: String,
}

impl Run {
    fn new(name: &str) -> Self {
        Run {
            dir: run_dir(&format!("hostile-{name}-")),
            domain: format!("hostile{name}{}", std::process::id()),
        }
    }

    fn path(&self) -> PathBuf {
        self.dir.path().join("run")
    }

    /// `--config`/`--set` of the small config in this run's directory and domain.
    fn args(&self, command: &[&str], overrides: &[&str]) -> Vec<String> {
        let domain = format!("run.domain={}", self.domain);
        let mut all = vec![domain.as_str()];
        all.extend(overrides);
        let mut args: Vec<String> = command.iter().map(|s| s.to_string()).collect();
        args.extend(config_args(self.dir.path(), &self.path(), &all));
        args
    }

    /// A store of this run started by hand, once it serves (its port file is written).
    fn start_store(&self) -> Proc {
        let path = self.path();
        let run_arg = path.display().to_string();
        let store = Proc::spawn("store", &self.args(&["store", "--run", &run_arg], &[]));
        wait_until("the store", within(60), || {
            path.join("ports/store.port").exists()
        });
        store
    }
}

impl Drop for Run {
    fn drop(&mut self) {
        let run = RunConfig {
            domain: self.domain.clone(),
            ..RunConfig::default()
        };
        if let Err(error) = domain::remove_domain(&run) {
            eprintln!("{error}");
        }
    }
}

fn scrape(run: &Path, process: &str) -> Vec<Sample> {
    let port = std::fs::read_to_string(run.join("ports").join(format!("{process}.port")))
        .expect("port file");
    let text = uavmeta_runtime::metrics::scrape("127.0.0.1", port.trim().parse().expect("port"))
        .expect("scrape");
    parse(&text).expect("metrics")
}

fn rejected(run: &Path, actor: u32, reason: &str) -> f64 {
    let actor = actor.to_string();
    let labels = [("actor", actor.as_str()), ("reason", reason)];
    sum(&scrape(run, "store"), names::TRANSITIONS_REJECTED, &labels)
}

/// `count` real steps of task `task`'s world from episode `episode`'s start, as an actor writes
/// them.
fn real_steps(config: &Config, task: usize, count: usize) -> Vec<Transition> {
    let mut world = World::new(&config.world, &config.tasks[task], 11);
    world.reset();
    (0..count)
        .map(|i| {
            let action = i % world.layout().action_count();
            let t = Transition {
                task: task as u32,
                seq: i as u64,
                ..record_step(&mut world, action)
            };
            if t.truncated {
                world.reset();
            }
            t
        })
        .collect()
}

/// Sends `batch` from `publisher` under `first_seq` until `arrived` holds (a first send may reach
/// a subscriber iceoryx2 has not connected yet).
fn send_until(
    publisher: &TransitionPublisher,
    first_seq: u64,
    batch: &[Transition],
    mut arrived: impl FnMut() -> bool,
) {
    wait_until("the store to take the batch", within(60), || {
        send(publisher, first_seq, batch);
        arrived()
    });
}

/// Sends `batch` once from `publisher`, numbered from `first_seq`.
fn send(publisher: &TransitionPublisher, first_seq: u64, batch: &[Transition]) {
    let mut loan = publisher.loan(first_seq, batch.len()).expect("loan");
    for (slot, t) in loan.slots_mut().iter_mut().zip(batch) {
        TransitionSlot::set_transition(slot, t);
    }
    loan.send().expect("send");
}

#[test]
fn a_hostile_publisher_leaves_the_store_running_the_dataset_clean_and_the_drops_counted() {
    let run = Run::new("pub");
    let path = run.path();
    let mut store = Proc::spawn(
        "store",
        &run.args(
            &["store", "--run", &path.display().to_string()],
            &["collect.transitions=1000000"],
        ),
    );
    wait_until("the store", within(60), || {
        path.join("ports/store.port").exists()
    });
    let run_dir = RunDir::open(&path).expect("run");
    let config = Config::load(&run_dir.config_file(), &[]).expect("config");
    let task = 1;
    let task_name = config.tasks[task].name.clone();
    let real_actor = ActorOptions {
        task: task_name.clone(),
        policy: "random".parse().expect("policy"),
        seed: 1,
        transitions: None,
    }
    .actor_id();

    let node = domain::node("hostile-publisher", &config.run).expect("node");
    let names_of_run = ServiceNames::new(run_dir.id());
    let service = transport::transition_service(&node, &names_of_run, &task_name, &config.run)
        .expect("service");
    let hostile = 4242;
    let publisher = TransitionPublisher::new(&service, &run_dir, &config, task as u32, hostile)
        .expect("publisher");
    let good = real_steps(&config, task, 16);
    type Corrupt = fn(&mut Transition);
    let cases: [(&str, Corrupt); 5] = [
        (names::NON_FINITE, |t| t.reward = f32::NAN),
        (names::ACTION, |t| t.action = 9999),
        (names::POSITION, |t| t.obs[0] = 65535),
        (names::AOI, |t| t.next_obs[2] = 65535),
        (names::REWARD, |t| t.reward = 1e30),
    ];
    for (reason, spoil) in cases {
        let mut batch = good.clone();
        spoil(&mut batch[5]);
        send_until(&publisher, 0, &batch, || {
            rejected(&path, hostile, reason) > 0.0
        });
    }
    // The real actor's id, numbered far ahead: stored, it would make every later batch of that
    // actor a duplicate.
    let forger = TransitionPublisher::new(&service, &run_dir, &config, task as u32, real_actor)
        .expect("forger");
    send_until(&forger, 1_000_000_000, &good, || {
        rejected(&path, real_actor, names::SEQUENCE_WINDOW) > 0.0
    });
    assert!(store.running(), "the store survived: {}", store.stderr());

    let actor = Proc::spawn(
        "actor",
        &[
            "actor",
            "--run",
            &path.display().to_string(),
            "--task",
            &task_name,
            "--seed",
            "1",
            "--policy",
            "random",
            "--transitions",
            "5000",
        ]
        .map(String::from),
    );
    actor.succeeds(within(120));
    wait_until(
        "the real actor's 5000 transitions stored",
        within(60),
        || {
            let samples = scrape(&path, "store");
            sum(
                &samples,
                names::DATASET_TRANSITIONS,
                &[("task", task_name.as_str())],
            ) == 5000.0
        },
    );
    let log = store.stderr();
    assert!(
        log.contains("dropped a batch that failed validation") && log.contains("actor=4242"),
        "a log line names the actor: {log}"
    );
    store.signal(libc::SIGTERM);
    store.succeeds(within(60));

    let file = path.join("datasets").join(format!("{task_name}.uavds"));
    let inspect = Proc::spawn(
        "inspect",
        &[
            "dataset".into(),
            "inspect".into(),
            file.display().to_string(),
        ],
    );
    let out = inspect.succeeds(within(60)).stdout;
    assert!(out.contains("every transition passes"), "{out}");
}

/// Issue #61: a publisher under a live actor's id, numbered ahead inside the store's sequence
/// window, would have the store drop the real actor's later transitions as duplicates and
/// acknowledge them. The actor sees an acknowledgement beyond what it sent and fails, naming
/// itself and what happened, rather than sending into the void.
#[test]
fn an_actor_acknowledged_beyond_what_it_sent_fails_naming_the_forged_id() {
    let run = Run::new("ackjump");
    let path = run.path();
    // A window of 4 x (2 x 4096 + 2) batches of 16, 524 288 transitions: room to forge far ahead
    // of the actor and still inside it.
    let sets = [
        "collect.transitions=1000000000",
        "run.subscriber_buffer=4096",
    ];
    let run_arg = path.display().to_string();
    let _store = Proc::spawn("store", &run.args(&["store", "--run", &run_arg], &sets));
    wait_until("the store", within(60), || {
        path.join("ports/store.port").exists()
    });
    let run_dir = RunDir::open(&path).expect("run");
    let config = Config::load(&run_dir.config_file(), &[]).expect("config");
    let (task, task_name) = (1, config.tasks[1].name.clone());
    // The forger takes the id of this actor: task, policy and seed make it.
    let options = ActorOptions {
        task: task_name.clone(),
        policy: "planner".parse().expect("policy"),
        seed: 1,
        transitions: None,
    };
    let args = [
        "actor", "--run", &run_arg, "--task", &task_name, "--seed", "1",
    ];
    // The planner, not random moves: a random actor publishes its 5 million transitions in
    // about 10 s, faster than a scrape of the store follows under load, so a number forged
    // ahead of the store's count could land behind the actor, or after it finished. The
    // planner's steps cost far more, so a batch forged 100 000 ahead of the count lands ahead of
    // the actor, inside the store's window, at the first try.
    let mut args: Vec<String> = args.map(String::from).to_vec();
    args.extend(["--policy", "planner", "--transitions", "5000000"].map(String::from));
    let mut actor = Proc::spawn("actor", &args);
    let stored = || {
        let samples = scrape(&path, "store");
        sum(
            &samples,
            names::DATASET_TRANSITIONS,
            &[("task", task_name.as_str())],
        )
    };
    // Tens of batches acknowledged: the actor has read the store's first acknowledgement, the
    // one that tells it where the store stands, before any forged batch moves the number.
    wait_until("the actor's first transitions stored", within(120), || {
        stored() >= 1000.0
    });
    let node = domain::node("forger", &config.run).expect("node");
    let service = transport::transition_service(
        &node,
        &ServiceNames::new(run_dir.id()),
        &task_name,
        &config.run,
    )
    .expect("service");
    let forger =
        TransitionPublisher::new(&service, &run_dir, &config, task as u32, options.actor_id())
            .expect("forger");
    // Numbered afresh at each try: the actor runs on while iceoryx2 connects the forger.
    let forged = real_steps(&config, task, 16);
    wait_until("the actor to stop", within(60), || {
        send(&forger, stored() as u64 + 100_000, &forged);
        !actor.running()
    });
    let out = actor.wait(within(60));
    assert!(!out.status.success(), "the actor went on: {}", out.stderr);
    let id = format!("actor {:08x}", options.actor_id());
    assert!(
        out.stderr.contains(&id)
            && out
                .stderr
                .contains("another publisher sends under this actor's id"),
        "{}",
        out.stderr
    );
}

/// Issue #61: one forged batch under an actor's id, numbered ahead of it, before the actor sends
/// (here while its online DQN agent trains): the store takes every transition the actor then
/// sends for a duplicate, the actor has sent everything and waits, and the dataset stays short
/// for ever. The launcher sees the dataset still while the actor went on, and ends the run with
/// an error naming the task, the actor and the duplicates, within run.hang_timeout_seconds.
#[test]
fn a_dataset_that_stops_growing_ends_the_launch_naming_the_task_and_the_actor() {
    let run = Run::new("stall");
    let path = run.path();
    let mut sets = support::DQN_RUN.to_vec();
    sets.push("run.hang_timeout_seconds=10");
    let launcher = Proc::spawn("launch", &run.args(&["launch"], &sets));
    wait_until("the store", within(60), || {
        path.join("ports/store.port").exists()
    });
    let run_dir = RunDir::open(&path).expect("run");
    let config = Config::load(&run_dir.config_file(), &[]).expect("config");
    let task_name = config.tasks[0].name.clone();
    let victim = ActorOptions {
        task: task_name.clone(),
        policy: "dqn-online".parse().expect("policy"),
        seed: config.collect.seed,
        transitions: None,
    };
    let node = domain::node("forger", &config.run).expect("node");
    let names_of_run = ServiceNames::new(run_dir.id());
    let service = transport::transition_service(&node, &names_of_run, &task_name, &config.run)
        .expect("service");
    let forger = TransitionPublisher::new(&service, &run_dir, &config, 0, victim.actor_id())
        .expect("forger");
    let stored = || {
        sum(
            &scrape(&path, "store"),
            names::DATASET_TRANSITIONS,
            &[("task", task_name.as_str())],
        )
    };
    // Inside the store's window (4 x (2 x 64 + 2) batches of 16), far beyond the 300 the actor
    // will send.
    send_until(&forger, 8000, &real_steps(&config, 0, 16), || {
        stored() > 0.0
    });
    let out = launcher.wait(within(300));
    assert!(
        !out.status.success(),
        "the launch ended well: {}",
        out.stderr
    );
    let expected = [
        format!("the dataset of task `{task_name}` has held 16 of its 300 transitions"),
        victim.process_name(),
        "as duplicates".to_string(),
    ];
    for needle in expected {
        assert!(
            out.stderr.contains(&needle),
            "no `{needle}` in: {}",
            out.stderr
        );
    }
}

#[test]
fn dataset_inspect_names_a_fabricated_transition_in_a_file_with_valid_crcs() {
    let dir = run_dir("hostile-inspect-");
    let config = Config::default();
    let task = &config.tasks[0];
    let file = dir.path().join("fabricated.uavds");
    let header = DatasetHeader::for_task(&config, &task.name).expect("header");
    let mut steps = real_steps(&config, 0, 40);
    steps[17].reward = -1e30;
    let mut writer = DatasetWriter::create(&file, header).expect("create");
    writer.append(&steps).expect("append");
    writer.sync().expect("sync");
    let saved = dir.path().join("fabricated.uavds.config.toml");
    std::fs::write(&saved, config.to_toml_string()).expect("config");
    let out = Proc::spawn(
        "inspect",
        &[
            "dataset".into(),
            "inspect".into(),
            file.display().to_string(),
        ],
    )
    .wait(within(60));
    assert!(
        !out.status.success(),
        "inspect passed a fabricated file: {}",
        out.stdout
    );
    assert!(out.stdout.contains("1 transitions FAIL"), "{}", out.stdout);
    assert!(
        out.stderr.contains("transition 17") && out.stderr.contains("(reward)"),
        "{}",
        out.stderr
    );
}

#[test]
fn a_launch_into_a_run_of_another_config_is_refused_naming_the_key_and_fresh_moves_it_aside() {
    let run = Run::new("reuse");
    let path = run.path();
    // A run made with the random policy: a store started by hand writes its config.toml.
    let store = run.start_store();
    store.signal(libc::SIGTERM);
    store.succeeds(within(60));
    let config_file = path.join("config.toml");
    let made_with = std::fs::read_to_string(&config_file).expect("config.toml");

    let other = ["collect.policy=\"stalest\""];
    let out = Proc::spawn("launch", &run.args(&["launch"], &other)).wait(within(60));
    assert!(!out.status.success(), "launched into another config's run");
    assert!(
        out.stderr.contains("collect.policy") && out.stderr.contains("--fresh"),
        "{}",
        out.stderr
    );
    assert!(!path.join("logs/launcher.log").exists() && !path.join("logs/store.log").exists());
    assert_eq!(
        std::fs::read_to_string(&config_file).expect("config"),
        made_with
    );
    let resumed =
        Proc::spawn("launch", &run.args(&["launch", "--resume"], &other)).wait(within(60));
    assert!(!resumed.status.success() && resumed.stderr.contains("collect.policy"));

    let launcher = Proc::spawn("launch", &run.args(&["launch", "--fresh"], &other));
    let moved = path.with_file_name("run.moved-1");
    wait_until("the fresh run's store", within(60), || {
        path.join("ports/store.port").exists()
    });
    assert_eq!(
        std::fs::read_to_string(moved.join("config.toml")).expect("the old run, moved"),
        made_with
    );
    let fresh = std::fs::read_to_string(&config_file).expect("the new config");
    assert!(fresh.contains("policy = \"stalest\""), "{fresh}");
    launcher.signal(libc::SIGTERM);
    launcher.wait(within(120));
}

#[test]
fn an_oversized_config_is_refused_before_any_process_starts() {
    let run = Run::new("big");
    let path = run.path();
    let cases: [(&[&str], &str); 8] = [
        (
            &["run.transitions_per_message=10000000"],
            "run.transitions_per_message",
        ),
        // Sizes within the config's rules whose memory this machine lacks (issue #61): each
        // refused naming its key and value, where the process would have aborted on allocation.
        (
            &[
                "collect.policy=dqn-online",
                "collect.dqn.replay_capacity=1000000000",
            ],
            "collect.dqn.replay_capacity = 1000000000",
        ),
        (
            &["collect.transitions=1000000000"],
            "collect.transitions = 1000000000",
        ),
        (
            &[
                "planner.beam_width=100000000",
                "planner.max_memory_mib=1000000000",
            ],
            "planner.beam_width = 100000000",
        ),
        (
            &["learner.hidden=[65536, 65536]"],
            "learner.hidden = [65536, 65536]",
        ),
        (
            &["world.grid_cells=1000", "world.devices=64"],
            "world.grid_cells",
        ),
        (&["collect.actors_per_task=1000"], "collect.actors_per_task"),
        // Within the config's caps, beyond this machine: 3 actors x 77 GB of shared memory.
        (
            &[
                "run.transitions_per_message=16384",
                "run.subscriber_buffer=4096",
            ],
            "/dev/shm has",
        ),
    ];
    for (overrides, needle) in cases {
        let out = Proc::spawn("launch", &run.args(&["launch"], overrides)).wait(within(60));
        assert!(!out.status.success(), "{overrides:?} was launched");
        assert!(out.stderr.contains(needle), "{overrides:?}: {}", out.stderr);
        assert!(
            !out.stderr.contains("panicked"),
            "{overrides:?}: {}",
            out.stderr
        );
        assert!(!path.exists(), "{overrides:?}: the run directory was made");
    }
}

#[test]
fn a_forged_shutdown_ends_the_launch_with_an_error_instead_of_a_wait_for_ever() {
    let run = Run::new("shut");
    let path = run.path();
    let launcher = Proc::spawn(
        "launch",
        &run.args(&["launch"], &["meta.meta_epochs=100000"]),
    );
    wait_until("the store and the meta-learner", within(120), || {
        ["store", "meta-learner"]
            .iter()
            .all(|p| path.join(format!("ports/{p}.port")).exists())
    });
    let run_dir = RunDir::open(&path).expect("run");
    let config = Config::load(&run_dir.config_file(), &[]).expect("config");
    let node = domain::node("forger", &config.run).expect("node");
    let service = transport::shutdown_service(&node, &ServiceNames::new(run_dir.id()), &config)
        .expect("shutdown service");
    let publisher = transport::control_publisher(&service).expect("publisher");
    let shutdown = payload::Shutdown {
        schema_version: payload::SCHEMA_VERSION,
        reserved: 0,
    };
    transport::announce(&publisher, shutdown).expect("announce");
    let out = launcher.wait(within(180));
    assert!(!out.status.success(), "a launch cut short exited 0");
    assert!(
        out.stderr.contains("by another process than this launcher"),
        "{}",
        out.stderr
    );
}

#[test]
fn an_actor_replaying_an_action_file_publishes_its_share_and_stops() {
    let run = Run::new("actions");
    let path = run.path();
    let run_arg = path.display().to_string();
    let store = run.start_store();
    // The small config's collect.transitions = 300 actions, one index a line.
    let file = run.dir.path().join("actions.txt");
    std::fs::write(&file, "3\n".repeat(300)).expect("actions");
    let policy = format!("actions:{}", file.display());
    let args = [
        "actor", "--run", &run_arg, "--task", "lambda-0", "--seed", "1", "--policy", &policy,
    ];
    Proc::spawn("actor", &args.map(String::from)).succeeds(within(120));
    wait_until("300 stored", within(60), || {
        let samples = scrape(&path, "store");
        sum(
            &samples,
            names::DATASET_TRANSITIONS,
            &[("task", "lambda-0")],
        ) == 300.0
    });
    drop(store);
}

#[test]
fn a_damaged_dataset_file_is_named_by_the_launch_not_left_to_a_timeout() {
    let run = Run::new("empty");
    let path = run.path();
    let store = run.start_store();
    store.signal(libc::SIGTERM);
    store.succeeds(within(60));
    let file = path.join("datasets/lambda-0.uavds");
    std::fs::write(&file, b"").expect("an empty dataset file");
    let out = Proc::spawn("launch", &run.args(&["launch"], &[])).wait(within(60));
    assert!(!out.status.success());
    assert!(
        out.stderr.contains("the store exited") && out.stderr.contains("lambda-0.uavds"),
        "{}",
        out.stderr
    );
}
