//! Runs: maximal sequences of consecutive steps of one episode, in which each transition's
//! `next_obs` is the next one's `obs`.
//!
//! Minari and d3rlpy store an episode as its observations followed by the final next
//! observation, so a transition whose successor is not in the data has to end an episode there.
//! A dataset rolled out by a heuristic is whole episodes; one sampled from a replay buffer (the
//! paper's, `dqn-online`), or N shots of any, is mostly runs of a step or two.

use uavmeta_proto::dataset::Transition;

/// `transitions` in runs, each in step order; runs ordered by actor, episode and step.
pub fn split(mut transitions: Vec<Transition>) -> Vec<Vec<Transition>> {
    transitions.sort_by_key(|t| (t.actor, t.episode, t.step));
    let mut runs: Vec<Vec<Transition>> = Vec::new();
    for t in transitions {
        match runs.last_mut() {
            Some(run) if continues(run.last().expect("a run is never empty"), &t) => run.push(t),
            _ => runs.push(vec![t]),
        }
    }
    runs
}

/// Whether `next` is the step right after `prev` in the same episode.
fn continues(prev: &Transition, next: &Transition) -> bool {
    (prev.actor, prev.episode, prev.step + 1) == (next.actor, next.episode, next.step)
        && prev.next_obs == next.obs
        && !prev.truncated
}

/// Whether `run` is a whole episode: from its first step to the time limit.
pub fn is_episode(run: &[Transition]) -> bool {
    matches!((run.first(), run.last()), (Some(first), Some(last)) if first.step == 0 && last.truncated)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn step(actor: u32, episode: u64, t: u32, truncated: bool) -> Transition {
        Transition {
            task: 0,
            actor,
            episode,
            step: t,
            seq: t as u64,
            obs: vec![t as u16, 0, 1],
            action: 0,
            reward: -1.0,
            next_obs: vec![t as u16 + 1, 0, 1],
            truncated,
        }
    }

    fn lengths(runs: &[Vec<Transition>]) -> Vec<usize> {
        runs.iter().map(Vec::len).collect()
    }

    #[test]
    fn consecutive_steps_form_one_run_whatever_their_order() {
        let runs = split(vec![
            step(0, 0, 2, true),
            step(0, 0, 0, false),
            step(0, 0, 1, false),
        ]);
        assert_eq!(lengths(&runs), [3]);
        assert_eq!(
            runs[0].iter().map(|t| t.step).collect::<Vec<_>>(),
            [0, 1, 2]
        );
        assert!(is_episode(&runs[0]));
    }

    #[test]
    fn a_missing_step_another_episode_or_actor_or_a_time_limit_ends_a_run() {
        let mut other_state = step(1, 0, 5, false);
        other_state.obs[1] = 9;
        let runs = split(vec![
            step(0, 0, 0, false),
            step(0, 0, 2, false),
            step(0, 1, 3, false),
            step(1, 1, 4, true),
            step(1, 1, 5, false),
            step(1, 0, 4, false),
            other_state,
        ]);
        assert_eq!(lengths(&runs), [1, 1, 1, 1, 1, 1, 1]);
        assert!(runs.iter().all(|run| !is_episode(run)));
    }
}
