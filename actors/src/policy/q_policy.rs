//! A Q-network acting in the world: its greedy policy, and the evaluator that scores it on the true
//! environment for `uavmeta_learner::train` (docs/MODEL.md section 5, "Evaluation") and, for the
//! model-based learner, rolls it out in the world the run's shots identify
//! (`uavmeta_world::identify`) from the shots' own states.
//!
//! The evaluator runs the same episodes as [`uavmeta_world::rollout::evaluate`] with a [`QPolicy`]
//! (every start cell of a deterministic world, Monte-Carlo episodes where the rain moves), but
//! steps all of them in lockstep (every episode lasts the horizon) so that each step is one forward
//! pass over an `[episodes, D]` batch rather than `episodes` passes over one row. Where the world
//! is deterministic its state is the observation, so an episode that comes to a state some episode
//! stood in before (another start cell's path, or its own lap) takes that episode's steps from
//! there on (`Paths`): the batch holds one row per state not seen yet, and a trained policy, whose
//! paths join its lap within a few steps, needs a small part of the rows (docs/MODEL.md section 5's
//! exact evaluation, unchanged: each start cell keeps its own return, AoI, power and outages).

use std::borrow::Borrow;
use std::collections::HashMap;

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use tch::Tensor;
use uavmeta_learner::qnet::QNetwork;
use uavmeta_learner::train::{EvaluatePolicy, Rollouts};
use uavmeta_proto::config::{Config, TaskConfig, WorldConfig};
use uavmeta_proto::dataset::Transition;
use uavmeta_proto::layout::Layout;
use uavmeta_proto::stats::{EpisodeMetrics, PolicyMetrics};

use uavmeta_world::identify::{identify, Unidentified};
use uavmeta_world::rollout::{evaluation_worlds, record_step, EpisodeTally, Policy};
use uavmeta_world::world::{Step, World};

/// `argmax_a Q(s, a)` on the normalised observation, of a network borrowed (`&QNetwork`) or owned.
pub struct QPolicy<Q: Borrow<QNetwork>> {
    q: Q,
    /// The normalised observation, reused every step.
    obs: Vec<f32>,
}

impl<Q: Borrow<QNetwork>> QPolicy<Q> {
    pub fn new(q: Q) -> Self {
        let obs = vec![0.0; q.borrow().obs_len()];
        Self { q, obs }
    }
}

impl<Q: Borrow<QNetwork>> Policy for QPolicy<Q> {
    fn act(&mut self, world: &World) -> usize {
        world.write_normalised(&mut self.obs);
        let obs = Tensor::from_slice(&self.obs).view([1, self.obs.len() as i64]); // [1, D]
        self.q.borrow().greedy(&obs).int64_value(&[0]) as usize
    }
}

/// Each episode of an evaluation: its start cell `(x, y)` and its metrics.
pub type StartEpisodes = Vec<((u16, u16), EpisodeMetrics)>;

/// Evaluation of greedy Q-policies on one task, always over the same episodes
/// ([`uavmeta_world::rollout::evaluation_worlds`]), and, once given the run's shots
/// ([`Evaluator::with_model`]), their rollouts in the world the shots identify.
#[derive(Debug, Clone)]
pub struct Evaluator {
    world: WorldConfig,
    task: TaskConfig,
    episodes: usize,
    seed: u64,
    /// The identified world, or why there is none.
    model: Result<Model, Unidentified>,
}

/// The world a run's shots identify, and where its rollouts start: the shots' own states.
#[derive(Debug, Clone)]
struct Model {
    world: World,
    /// Each distinct (state, step) of the shots, in the order the shots first show it.
    starts: Vec<(Vec<u16>, u32)>,
}

impl Evaluator {
    pub fn new(world: &WorldConfig, task: &TaskConfig, episodes: usize, seed: u64) -> Self {
        Self {
            world: world.clone(),
            task: task.clone(),
            episodes,
            seed,
            model: Err(Unidentified::NoShots),
        }
    }

    /// This evaluator with the world `shots` identify under the config's world form
    /// ([`uavmeta_world::identify`]: the task is never read), where its rollouts
    /// ([`EvaluatePolicy::rollouts`]) start from the shots' states. Where the shots identify
    /// nothing (they show rain, or are not steps of this world) it rolls out nothing.
    pub fn with_model(self, shots: &[Transition]) -> Self {
        let model = identify(&self.world, shots).map(|identified| {
            tracing::debug!(
                devices_fitted = identified.devices_fitted,
                "the shots identify the world"
            );
            Model::new(identified.world, shots)
        });
        if let Err(why) = &model {
            tracing::debug!(%why, "the shots identify no world");
        }
        Self { model, ..self }
    }

    /// Why the shots given to [`Evaluator::with_model`] identify no world, if they do not.
    pub fn unidentified(&self) -> Option<Unidentified> {
        self.model.as_ref().err().copied()
    }

    /// The evaluator a config asks for: `learner.eval_episodes` episodes seeded
    /// `learner.eval_seed`.
    pub fn from_config(config: &Config, task: &TaskConfig) -> Self {
        Self::new(
            &config.world,
            task,
            config.learner.eval_episodes,
            config.learner.eval_seed,
        )
    }
}

impl Evaluator {
    /// Each evaluation episode of `q`'s greedy policy: its start cell `(x, y)` and its metrics, in
    /// the order of [`evaluation_worlds`].
    pub fn episodes(&self, q: &QNetwork) -> StartEpisodes {
        self.run(q).0
    }

    /// [`Evaluator::episodes`], and how many observations went through `q` (at most episodes x
    /// horizon: episodes that meet in one state of a deterministic world share their remaining
    /// steps, so the batch shrinks as the greedy policy's paths join).
    fn run(&self, q: &QNetwork) -> (StartEpisodes, usize) {
        lockstep(
            evaluation_worlds(&self.world, &self.task, self.episodes, self.seed),
            q,
        )
    }
}

/// Each episode of `worlds` (each reset first) under `q`'s greedy policy, stepped in lockstep to
/// the horizon: its start cell and metrics, and how many observations went through `q`.
fn lockstep(mut worlds: Vec<World>, q: &QNetwork) -> (StartEpisodes, usize) {
    if worlds.is_empty() {
        return (Vec::new(), 0);
    }
    worlds.iter_mut().for_each(World::reset);
    let starts: Vec<(u16, u16)> = worlds
        .iter()
        .map(|w| (w.observation()[0], w.observation()[1]))
        .collect();
    let (e, d) = (worlds.len(), q.obs_len());
    let horizon = worlds[0].horizon() as usize;
    let mut paths = Paths::new(e, horizon, worlds[0].is_deterministic());
    let mut obs = vec![0f32; e * d];
    let mut actions = vec![0i64; e];
    let mut rows = 0;
    for t in 0..horizon {
        paths.join(&worlds, t);
        let live = paths.live().to_vec();
        rows += live.len();
        for (&w, row) in live.iter().zip(obs.chunks_exact_mut(d)) {
            worlds[w].write_normalised(row);
        }
        let n = live.len();
        if n > 0 {
            let batch = Tensor::from_slice(&obs[..n * d]).view([n as i64, d as i64]); // [n, D]
            q.greedy(&batch).copy_data(&mut actions, n); // [n]
        }
        for (&w, &action) in live.iter().zip(&actions) {
            paths.record(w, t, worlds[w].step(action as usize));
        }
    }
    let tallies = (0..e).map(|w| {
        let mut tally = EpisodeTally::default();
        (0..horizon).for_each(|t| tally.add(paths.step(w, t)));
        tally.finish()
    });
    let episodes = starts.into_iter().zip(tallies).collect();
    (episodes, rows)
}

/// The episodes of one lockstep evaluation and the step each took at each t. On a deterministic
/// world the state is the observation, and the policy and the step depend on nothing else (not on
/// t: the horizon only ends the episode), so once an episode stands in a state that some episode
/// stood in at t0 (itself, on a lap, or another one, at the same step or earlier) its steps from
/// now on are that episode's from t0 on: it *follows* it, lag t - t0, and needs no forward pass.
struct Paths {
    horizon: usize,
    deterministic: bool,
    /// The step of episode w at t, at `[w * horizon + t]`, for the steps it was live.
    steps: Vec<Option<Step>>,
    /// `None` while episode w is stepped itself, then (episode, lag) it follows.
    follows: Vec<Option<(usize, usize)>>,
    /// Where each state was first stood in: (episode, t).
    seen: HashMap<Box<[u16]>, (usize, usize)>,
    live: Vec<usize>,
}

impl Paths {
    fn new(episodes: usize, horizon: usize, deterministic: bool) -> Self {
        Self {
            horizon,
            deterministic,
            steps: vec![None; episodes * horizon],
            follows: vec![None; episodes],
            seen: HashMap::new(),
            live: (0..episodes).collect(),
        }
    }

    /// Before step t: every live episode whose state was stood in before (or just now, by an
    /// episode earlier in the list) starts following where it was first.
    fn join(&mut self, worlds: &[World], t: usize) {
        if !self.deterministic {
            return;
        }
        let (seen, follows) = (&mut self.seen, &mut self.follows);
        self.live
            .retain(|&w| match seen.get(worlds[w].observation()) {
                Some(&(first, t0)) => {
                    follows[w] = Some((first, t - t0));
                    false
                }
                None => {
                    seen.insert(worlds[w].observation().into(), (w, t));
                    true
                }
            });
    }

    /// The episodes stepped by the policy at this step.
    fn live(&self) -> &[usize] {
        &self.live
    }

    fn record(&mut self, w: usize, t: usize, step: Step) {
        self.steps[w * self.horizon + t] = Some(step);
    }

    /// Step t of episode w: its own if it was live then, else the step of whom it follows. A lag
    /// of 0 leads to an episode that was live when w joined it (and was followed only later, if
    /// at all), a lag above 0 back in time, so the walk ends at a recorded step.
    fn step(&self, mut w: usize, mut t: usize) -> &Step {
        loop {
            if let Some(step) = &self.steps[w * self.horizon + t] {
                return step;
            }
            let (first, lag) = self.follows[w].expect("an unrecorded step is a following one");
            (w, t) = (first, t - lag);
        }
    }
}

impl EvaluatePolicy for Evaluator {
    fn evaluate(&mut self, q: &QNetwork) -> PolicyMetrics {
        let episodes: Vec<EpisodeMetrics> = self.episodes(q).into_iter().map(|(_, m)| m).collect();
        PolicyMetrics::from_episodes(&episodes)
    }

    fn rollouts(&mut self, q: &QNetwork, ask: Rollouts) -> Option<Vec<Transition>> {
        let model = self.model.as_ref().ok()?;
        Some(model.rollouts(q, ask))
    }
}

impl Model {
    fn new(world: World, shots: &[Transition]) -> Self {
        let mut seen = std::collections::HashSet::new();
        let aoi_max = world.aoi_max();
        let starts = shots
            .iter()
            .filter(|t| {
                t.step < world.horizon() && Layout::aoi(&t.obs).iter().all(|&a| a <= aoi_max)
            })
            .map(|t| (t.obs.clone(), t.step))
            .filter(|start| seen.insert(start.clone()))
            .collect();
        Self { world, starts }
    }

    /// One branch from each start of `ceil(ask.rows / starts)` steps (fewer where the horizon
    /// comes first) under `q`, acting uniformly at random with probability `ask.epsilon` and
    /// greedily otherwise (draws seeded `ask.seed`), stepped in lockstep: one forward pass per
    /// step.
    fn rollouts(&self, q: &QNetwork, ask: Rollouts) -> Vec<Transition> {
        let Rollouts {
            rows,
            epsilon,
            seed,
        } = ask;
        let length = rows.div_ceil(self.starts.len().max(1)) as u32;
        let mut worlds: Vec<World> = self
            .starts
            .iter()
            .map(|(obs, step)| {
                let mut world = self.world.clone();
                world.reset();
                world.set_observation(obs);
                world.set_t(*step);
                world
            })
            .collect();
        let ends: Vec<u32> = self
            .starts
            .iter()
            .map(|(_, step)| (step + length).min(self.world.horizon()))
            .collect();
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let (d, actions) = (q.obs_len(), q.actions());
        let mut steps = Vec::with_capacity(rows);
        let mut obs = Vec::with_capacity(worlds.len() * d);
        let mut greedy = vec![0i64; worlds.len()];
        loop {
            let live: Vec<usize> = (0..worlds.len())
                .filter(|&w| worlds[w].t() < ends[w])
                .collect();
            if live.is_empty() {
                return steps;
            }
            obs.resize(live.len() * d, 0.0);
            for (&w, row) in live.iter().zip(obs.chunks_exact_mut(d)) {
                worlds[w].write_normalised(row);
            }
            let batch = Tensor::from_slice(&obs).view([live.len() as i64, d as i64]); // [n, D]
            q.greedy(&batch).copy_data(&mut greedy, live.len()); // [n]
            for (&w, &g) in live.iter().zip(&greedy) {
                let action = match rng.random::<f64>() < epsilon {
                    true => rng.random_range(0..actions),
                    false => g as usize,
                };
                let seq = steps.len() as u64;
                steps.push(Transition {
                    episode: w as u64,
                    seq,
                    ..record_step(&mut worlds[w], action)
                });
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use uavmeta_proto::config::{Config, RainZone};

    use super::*;
    use uavmeta_learner::qnet::QNetworkConfig;
    use uavmeta_world::rollout::{evaluate, evaluate_episodes};
    use uavmeta_world::world::Move;

    fn assert_metrics_close(batched: &PolicyMetrics, single: &PolicyMetrics) {
        assert_eq!(batched.episodes, single.episodes);
        let pairs = [
            (batched.ret, single.ret),
            (batched.aoi, single.aoi),
            (batched.power_mw, single.power_mw),
            (batched.outages, single.outages),
        ];
        for (b, s) in pairs {
            assert!(
                (b.mean - s.mean).abs() <= 1e-9 && (b.ci95 - s.ci95).abs() <= 1e-9,
                "batched {batched:?}\nsingle  {single:?}"
            );
        }
    }

    /// The lockstep evaluation runs exactly the episodes of `rollout::evaluate` with a `QPolicy`:
    /// on a clear task and on a rain task whose zone moves (so the worlds' random streams matter).
    #[test]
    fn batched_evaluation_equals_episode_by_episode() {
        tch::set_num_threads(1);
        let config = Config::default();
        let rain = TaskConfig {
            rain_moves_every: Some(10),
            ..TaskConfig::one_off(
                300.0,
                Some(RainZone {
                    x0: 3,
                    y0: 3,
                    x1: 6,
                    y1: 6,
                }),
            )
        };
        let tasks = [TaskConfig::one_off(100.0, None), rain];
        let (obs_len, actions) = (
            config.world.layout().observation_len(),
            config.world.layout().action_count(),
        );
        for (net_seed, task) in tasks.iter().enumerate() {
            let q =
                QNetworkConfig::new(obs_len, actions, &config.learner.hidden).init(net_seed as u64);
            for episodes in [1, 7] {
                let seed = 31 + episodes as u64;
                let batched = Evaluator::new(&config.world, task, episodes, seed).evaluate(&q);
                let single = evaluate(&config.world, task, &mut QPolicy::new(&q), episodes, seed);
                // Every start cell on the clear task; the Monte-Carlo episodes where rain moves.
                let expected = if task.rain_moves_every.is_some() {
                    episodes
                } else {
                    100
                };
                assert_eq!(batched.episodes, expected);
                assert_metrics_close(&batched, &single);
                // The rain task's episodes do fly through rain, so outages are compared too.
                assert_eq!(single.outages.mean > 0.0, task.rain.is_some());
            }
        }
    }

    /// Episodes that meet share their steps and keep their own returns. The network's greedy
    /// action is "fly west, serve the stalest device" (Q(west, k) = A_k / aoi_max, every other
    /// action -1): the AoI is the same in every episode at every step and settles into a round
    /// robin of period K, and every start cell of a grid row reaches the west edge within L - 1
    /// steps. So the episodes of a row meet there (lag 0), and each row's path then laps (it
    /// follows itself, lag K): after the first 2K or so steps no episode needs a forward pass.
    #[test]
    fn episodes_that_meet_share_their_steps() {
        tch::set_num_threads(1);
        let config = Config::default();
        let task = TaskConfig::one_off(300.0, None);
        let (obs_len, actions) = (
            config.world.layout().observation_len(),
            config.world.layout().action_count(),
        );
        let k = config.world.devices;
        let q = QNetworkConfig::new(obs_len, actions, &config.learner.hidden).init(3);
        let params = q.parameters();
        let west = config.world.layout().action(Move::West.index(), 0);
        tch::no_grad(|| {
            for p in &params {
                let _ = p.shallow_clone().zero_();
            }
            for i in 0..k as i64 {
                // Hidden units i of both layers carry A_i / aoi_max (input 2 + i) through the
                // ReLUs.
                let _ = params[0].get(i).get(2 + i).fill_(1.0);
                let _ = params[2].get(i).get(i).fill_(1.0);
                let _ = params[4].get(west as i64 + i).get(i).fill_(1.0);
            }
            let _ = params[5].shallow_clone().fill_(-1.0);
            let _ = params[5].narrow(0, west as i64, k as i64).fill_(0.0);
        });
        let evaluator = Evaluator::new(&config.world, &task, 1, 0);
        let (batched, rows) = evaluator.run(&q);
        let single = evaluate_episodes(&config.world, &task, &mut QPolicy::new(&q), 1, 0);
        assert_eq!(batched.len(), single.len());
        for ((_, b), s) in batched.iter().zip(&single) {
            assert_eq!(b, s);
        }
        // Start cells further east stay apart for longer, so returns differ within a grid row.
        assert_ne!(single[0].ret, single[9].ret);
        let (episodes, horizon) = (single.len(), config.world.horizon as usize);
        assert!(
            rows <= episodes * 3 * k && rows < episodes * horizon / 3,
            "{rows} rows of {}",
            episodes * horizon
        );
    }

    /// `steps` transitions of uniformly random actions from random start cells, as an actor
    /// records them.
    fn random_shots(config: &Config, task: &TaskConfig, steps: usize) -> Vec<Transition> {
        let policy = Box::new(uavmeta_world::heuristics::RandomPolicy::new(6));
        let mut shots = Vec::new();
        crate::collect::Collector::new(&config.world, task, 0, 0, policy, 5)
            .fill(steps, &mut shots);
        shots
    }

    /// Every (state, action) of `world` from a few AoI vectors: the reward and next state.
    fn outcomes(world: &World) -> Vec<(f64, Vec<u16>)> {
        let (grid, k) = (world.grid_cells() as u16, world.devices());
        let mut out = Vec::new();
        let mut next = vec![0u16; world.layout().observation_len()];
        for aoi in [1u16, 3, 7] {
            for c in 0..grid * grid {
                let obs: Vec<u16> = [c % grid, c / grid]
                    .into_iter()
                    .chain((0..k as u16).map(|j| 1 + (j * aoi) % world.aoi_max()))
                    .collect();
                for action in 0..world.layout().action_count() {
                    let reward = world
                        .outcome(&obs, action, false, false, &mut next)
                        .unwrap();
                    out.push((reward, next.clone()));
                }
            }
        }
        out
    }

    /// The fit reads the shots alone: under configs whose task names lambda 0, lambda 2000 or
    /// no rain, lambda-300's shots give the same fitted rewards for every state and action, the
    /// true task's where the shots determine every device; a rain task's shots say it has rain
    /// under a config that names none.
    #[test]
    fn the_fitted_world_is_learnt_from_the_shots_alone() {
        let mut config = Config::default();
        config.world.noise_dbm = -90.0;
        let truth = TaskConfig::one_off(300.0, None);
        let shots = random_shots(&config, &truth, 2000);
        let told = [0.0, 2000.0, 300.0].map(|lambda| TaskConfig::one_off(lambda, None));
        let fitted: Vec<Vec<(f64, Vec<u16>)>> = told
            .iter()
            .map(|task| {
                let evaluator = Evaluator::from_config(&config, task).with_model(&shots);
                outcomes(&evaluator.model.unwrap().world)
            })
            .collect();
        assert!(fitted.iter().all(|f| *f == fitted[0]));
        let true_outcomes = outcomes(&World::new(&config.world, &truth, 0));
        for ((model, next), (reward, true_next)) in fitted[0].iter().zip(&true_outcomes) {
            assert_eq!(next, true_next);
            assert!(
                (model - reward).abs() < 1e-4 * reward.abs(),
                "{model} {reward}"
            );
        }
        let zone = RainZone {
            x0: 3,
            y0: 3,
            x1: 6,
            y1: 6,
        };
        let rain = random_shots(&config, &TaskConfig::one_off(300.0, Some(zone)), 2000);
        for task in &told {
            let evaluator = Evaluator::from_config(&config, task).with_model(&rain);
            assert!(
                matches!(evaluator.unidentified(), Some(Unidentified::Rain(n)) if n > 0),
                "{:?}",
                evaluator.unidentified()
            );
        }
    }

    fn ask(rows: usize, epsilon: f64, seed: u64) -> Rollouts {
        Rollouts {
            rows,
            epsilon,
            seed,
        }
    }

    /// The rollouts branch from the shots' own states, one branch of ceil(rows / starts) steps
    /// each, in the identified world: their rewards are the true world's where the shots
    /// determine every device; epsilon 1 acts otherwise, and the seed fixes the draws. Where the
    /// shots identify nothing there are none.
    #[test]
    fn rollouts_are_steps_of_the_identified_world_from_the_shots_states() {
        tch::set_num_threads(1);
        let config = Config::default();
        let task = TaskConfig::one_off(2000.0, None);
        let (obs_len, actions) = (
            config.world.layout().observation_len(),
            config.world.layout().action_count(),
        );
        let shots = random_shots(&config, &task, 2000);
        let mut evaluator = Evaluator::from_config(&config, &task).with_model(&shots);
        let q = QNetworkConfig::new(obs_len, actions, &config.learner.hidden).init(1);
        let greedy = evaluator.rollouts(&q, ask(10_000, 0.0, 7)).unwrap();
        let first: std::collections::HashSet<(Vec<u16>, u32)> = greedy
            .iter()
            .filter(|t| t.seq == t.episode)
            .map(|t| (t.obs.clone(), t.step))
            .collect();
        let shot_states: std::collections::HashSet<(Vec<u16>, u32)> =
            shots.iter().map(|t| (t.obs.clone(), t.step)).collect();
        assert_eq!(
            first, shot_states,
            "one branch from every state of the shots"
        );
        assert!(greedy.len() >= 10_000 - shots.len() * 5 && greedy.len() <= 10_000 + shots.len());
        let truth = World::new(&config.world, &task, 0);
        let mut next = vec![0u16; obs_len];
        for t in &greedy {
            let reward = truth.outcome(&t.obs, usize::from(t.action), false, false, &mut next);
            let reward = reward.unwrap();
            assert_eq!(next, t.next_obs);
            let logged = f64::from(t.reward);
            assert!(
                (reward - logged).abs() < 1e-5 * reward.abs(),
                "{reward} {t:?}"
            );
        }
        let random = evaluator.rollouts(&q, ask(10_000, 1.0, 7)).unwrap();
        assert_ne!(random, greedy);
        assert_eq!(random, evaluator.rollouts(&q, ask(10_000, 1.0, 7)).unwrap());
        assert_ne!(random, evaluator.rollouts(&q, ask(10_000, 1.0, 8)).unwrap());
        let rain = TaskConfig::one_off(
            2000.0,
            Some(RainZone {
                x0: 3,
                y0: 3,
                x1: 6,
                y1: 6,
            }),
        );
        let mut rainy =
            Evaluator::from_config(&config, &rain).with_model(&random_shots(&config, &rain, 2000));
        assert!(rainy.rollouts(&q, ask(100, 0.0, 7)).is_none());
        assert!(Evaluator::from_config(&config, &task)
            .rollouts(&q, ask(100, 0.0, 7))
            .is_none());
    }
}
