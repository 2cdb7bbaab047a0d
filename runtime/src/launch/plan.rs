//! The children of a run, in the order they start and stop: store, tunnel, actors,
//! meta-learner, evaluator.

use super::*;

/// What kind of child a process is: decides the stop order and when the run is done.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
pub(super) enum Role {
    Actor,
    MetaLearner,
    Evaluator,
    /// The run's end of the tunnel to remote actor hosts (`tunnel.listen`).
    Tunnel,
    Store,
}

pub(super) struct Supervised {
    pub(super) name: String,
    pub(super) role: Role,
    /// An actor's task.
    pub(super) task: Option<String>,
    pub(super) args: Vec<String>,
    pub(super) child: Option<Child>,
    /// Failures so far; each one is followed by a restart until `run.max_restarts`.
    pub(super) failures: u32,
    pub(super) restart_at: Option<Instant>,
    /// Exited successfully: not restarted.
    pub(super) done: bool,
    /// The sweep of its resources requested when it last failed.
    pub(super) cleanup: Option<u64>,
}

/// The children of a run: store, actors, meta-learner, evaluator.
pub(super) fn plan(run: &RunDir, config: &Config) -> Result<Vec<Supervised>, LaunchError> {
    let policy: PolicySpec =
        config
            .collect
            .policy
            .parse()
            .map_err(
                |e: uavmeta_world::heuristics::PolicyError| LaunchError::Policy {
                    origin: config.origin.clone(),
                    message: e.to_string(),
                },
            )?;
    let run_arg = run.root().display().to_string();
    let child = |name: String, role: Role, args: Vec<String>| Supervised {
        name,
        role,
        task: None,
        args,
        child: None,
        failures: 0,
        restart_at: None,
        done: false,
        cleanup: None,
    };
    let mut children = vec![child(
        store::PROCESS.into(),
        Role::Store,
        vec!["store".into(), "--run".into(), run_arg.clone()],
    )];
    for task in &config.tasks {
        for i in 0..config.collect.actors_per_task {
            let seed = config.collect.seed.wrapping_add(i as u64);
            let options = ActorOptions {
                task: task.name.clone(),
                policy: policy.clone(),
                seed,
                transitions: None,
            };
            let args = vec![
                "actor".into(),
                "--run".into(),
                run_arg.clone(),
                "--task".into(),
                task.name.clone(),
                "--seed".into(),
                seed.to_string(),
            ];
            children.push(Supervised {
                task: Some(task.name.clone()),
                ..child(options.process_name(), Role::Actor, args)
            });
        }
    }
    if !config.tunnel.listen.is_empty() {
        children.push(child(
            TUNNEL_PROCESS.into(),
            Role::Tunnel,
            vec![
                "tunnel".into(),
                "serve".into(),
                "--run".into(),
                run_arg.clone(),
            ],
        ));
    }
    if config.tasks_with_role(TaskRole::MetaTrain).next().is_some()
        && config.tasks_with_role(TaskRole::MetaTest).next().is_some()
    {
        children.push(child(
            meta_learner::PROCESS.into(),
            Role::MetaLearner,
            vec!["meta-learner".into(), "--run".into(), run_arg.clone()],
        ));
        children.push(child(
            evaluator::PROCESS.into(),
            Role::Evaluator,
            vec!["evaluator".into(), "--run".into(), run_arg],
        ));
    }
    Ok(children)
}
