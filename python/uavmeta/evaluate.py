"""Scoring a policy as the tables and the command line do.

``evaluate(policy, task)`` runs the world crate's own evaluation through the binding: with
``exact=True`` one episode from every start cell where the world is deterministic (fixed
Monte-Carlo episodes where the rain moves), as ``uavmeta env rollout --exact`` and ``uavmeta
eval`` run it, so the figures are the command line's to the digit. ``references(task)`` gives the
reference rows of every results table (random, stalest, greedy, planner) evaluated the same way,
and ``normalised_score`` puts a return between them: 0 is the random policy, 100 the planner (as
D4RL normalises between random and expert).
"""

import numbers
from dataclasses import dataclass, field
from typing import Tuple

import numpy as np

from . import _args
from ._uavmeta import Evaluation as _Evaluation
from ._uavmeta import evaluate_spec as _evaluate_spec
from ._uavmeta import reference_names as _reference_names

#: The reference policies of every results table, in order.
REFERENCES = tuple(_reference_names())


@dataclass(frozen=True)
class Estimate:
    """A mean over episodes with the half-width of its 95% confidence interval (Student's t),
    as the command line computes it."""

    mean: float
    ci95: float

    def __str__(self):
        return f"{self.mean:.3f} ± {self.ci95:.3f}"


@dataclass(frozen=True)
class Score:
    """A policy's evaluation on one task.

    ``ret``, ``aoi``, ``power_mw`` and ``outages`` are :class:`Estimate`\\ s over the episodes;
    ``episodes`` holds the per-episode arrays (``start`` (E, 2) cells, ``ret``, ``aoi``,
    ``power_mw``, ``outages``); ``trapped`` lists the start cells whose episode returned less
    than the random policy's mean on the same worlds (``uavmeta eval --per-episode``), or is
    None when not asked for."""

    task: str
    lam: float
    exact: bool
    seed: int
    ret: Estimate
    aoi: Estimate
    power_mw: Estimate
    outages: Estimate
    episodes: dict = field(repr=False)
    trapped: Tuple[Tuple[int, int], ...] = None

    @property
    def num_episodes(self):
        return len(self.episodes["ret"])


def _score(raw, env, exact, seed, trapped=None):
    mean = raw.pop("mean")
    info = env.task_of(0)
    return Score(
        task=info["name"],
        lam=info["lam"],
        exact=exact,
        seed=seed,
        ret=Estimate(*mean["ret"]),
        aoi=Estimate(*mean["aoi"]),
        power_mw=Estimate(*mean["power_mw"]),
        outages=Estimate(*mean["outages"]),
        episodes=raw,
        trapped=trapped,
    )


def task_env(task=None, **kwargs):
    """The env a task argument means: an env as it is (``UavEnv``, ``VectorEnv`` of one task,
    or a ``gymnasium.make`` of them), a task name of ``config=``, a lambda, or a dict of
    ``lam``, ``rain``, ``rain_moves_every``, ``layout`` (as ``env.task_of(i)`` returns one);
    ``kwargs`` go to ``UavEnv`` as its task and world arguments (``config=``, ``normalised=``,
    world keys)."""
    from .env import UavEnv

    for e in (task, getattr(task, "unwrapped", None)):
        if getattr(e, "_worlds", None) is not None:
            if kwargs:
                raise TypeError(
                    f"task = {task!r} is an env: expected no further task arguments, got "
                    f"{sorted(kwargs)}"
                )
            worlds = e._worlds
            if worlds.resamples_tasks or (worlds.task_count or 0) > 1:
                raise ValueError(
                    f"task = {task!r} runs several tasks: expected an env of one task (pass "
                    "one of env.tasks)"
                )
            return e
    if task is None:
        return UavEnv(**kwargs)
    if isinstance(task, str):
        return UavEnv(task=task, **kwargs)
    if isinstance(task, numbers.Real) and not isinstance(task, bool):
        return UavEnv(lam=task, **kwargs)
    if isinstance(task, dict):
        entry = _args.task_entry(task, 0)
        if entry[4] is not None:  # a layout of its own: a task list takes it
            from .vector import VectorEnv

            return VectorEnv(1, tasks=[task], **kwargs)
        name, lam, rain, moves, _ = entry
        return UavEnv(task=name, lam=lam, rain=rain, rain_moves_every=moves, **kwargs)
    raise TypeError(
        f"task = {task!r}: expected an env, a task name, a lambda or a dict of lam, rain, "
        "rain_moves_every, layout"
    )


def _episodes_and_seed(env, episodes, seed, exact):
    if not isinstance(exact, (bool, np.bool_)):
        raise TypeError(f"exact = {exact!r}: expected True or False")
    worlds = env._worlds
    episodes = worlds.eval_episodes if episodes is None else episodes
    seed = worlds.eval_seed if seed is None else seed
    episodes = _args.natural("episodes", episodes, upper=2**64)
    if episodes == 0:
        raise ValueError("episodes = 0: expected at least 1 episode")
    return episodes, _args.seed(seed)


def _spec_of(policy):
    """The command line's ``--policy`` spelling of a policy the world crate runs itself."""
    from .policies import HeuristicPolicy

    if isinstance(policy, str):
        return policy
    if isinstance(policy, HeuristicPolicy):
        return policy.name
    return None


def _actions_of(policy):
    """A function from an (E, 2 + K) batch and the step t to E action indices."""
    predict = getattr(policy, "predict", None)
    if predict is not None and not callable(policy):  # a Stable-Baselines3 model
        return lambda obs, t: predict(obs, deterministic=True)[0]
    if not callable(policy):
        raise TypeError(
            f"policy = {policy!r}: expected a policy name (random, stalest, greedy, planner, "
            "eps:P, actions:FILE), a callable policy(obs, t) -> actions, or an SB3 model"
        )
    try:
        import inspect

        takes_t = "t" in inspect.signature(policy).parameters
    except (TypeError, ValueError):
        takes_t = False
    return (lambda obs, t: policy(obs, t=t)) if takes_t else (lambda obs, t: policy(obs))


def evaluate(policy, task=None, *, exact=True, episodes=None, seed=None, trapped=True, **kwargs):
    """Evaluates ``policy`` on ``task`` as the tables do; returns a :class:`Score`.

    ``policy`` is a name the command line's ``--policy`` takes (``"random"``, ``"stalest"``,
    ``"greedy"``, ``"planner"``, ``"eps:P"``, ``"actions:FILE"``, ``"q:P:CHECKPOINT"``) or a
    heuristic of
    :mod:`uavmeta.policies`, run in Rust exactly as ``uavmeta env rollout --policy NAME`` runs
    it; or any callable ``policy(obs)`` (or ``policy(obs, t=t)``) mapping an (E, 2 + K) batch
    to E action indices, such as :func:`uavmeta.policies.checkpoint`, or a Stable-Baselines3
    model (its ``predict(obs, deterministic=True)``): every evaluation episode is then stepped
    in lockstep, one batch per step, so a deterministic policy scores as the command line
    scores it (``uavmeta eval --checkpoint`` for a saved Q-network).

    ``task``: see :func:`task_env` (an env, a task name with ``config=``, a lambda, a dict);
    observations reach the policy as that env gives them (``normalised=True`` or raw).
    ``exact``: one episode per start cell (``--exact``), else ``episodes`` Monte-Carlo
    episodes seeded ``seed`` (``uavmeta env rollout --episodes N --seed S``). ``episodes`` and
    ``seed`` default to the config's ``learner.eval_episodes`` and ``learner.eval_seed``, as
    ``uavmeta eval`` and the tables use. ``trapped``: also list the start cells whose return
    falls below the random policy's mean.
    """
    env = task_env(task, **kwargs)
    episodes, seed = _episodes_and_seed(env, episodes, seed, exact)
    worlds = env._worlds
    spec = _spec_of(policy)
    if spec is not None and spec.startswith("q:"):  # a saved Q-network: numpy, in lockstep
        from .policies import make

        try:
            policy, spec = make(spec, env), None
        except (ValueError, TypeError, OSError) as e:  # named as the argument it came from
            try:
                named = type(e)(f"policy = {spec!r}: {e}")
            except Exception:
                raise e from None
            raise named from e
    if spec is not None:
        raw = _evaluate_spec(worlds, spec, episodes=episodes, seed=seed, exact=bool(exact))
    else:
        act = _actions_of(policy)
        run = _Evaluation(worlds, episodes=episodes, seed=seed, exact=bool(exact))
        while run.t < run.horizon:
            obs = run.observations()
            actions = np.asarray(act(obs, run.t))
            if actions.dtype.kind not in "iu":
                raise TypeError(
                    f"the policy returned actions of dtype {actions.dtype}: expected integer "
                    "action indices"
                )
            if actions.shape != (len(obs),):
                raise ValueError(
                    f"the policy returned actions of shape {actions.shape} for {len(obs)} "
                    f"observations: expected ({len(obs)},)"
                )
            if actions.dtype.kind == "u" and actions.size and actions.max() > np.iinfo(np.int64).max:
                i = int(actions.argmax())
                raise ValueError(
                    f"the policy's action for episode {i} = {int(actions[i])}: expected an "
                    f"action index in 0..{env.action_space.n}"
                )
            run.step(np.ascontiguousarray(actions, dtype=np.int64))
        raw = run.results()
    cells = None
    if trapped:
        floor = _evaluate_spec(worlds, "random", episodes=episodes, seed=seed, exact=bool(exact))
        below = raw["ret"] < floor["mean"]["ret"][0]
        cells = tuple(tuple(int(v) for v in c) for c in raw["start"][below])
    return _score(raw, env, exact, seed, cells)


_REFERENCE_CACHE = {}


def references(task=None, *, exact=True, episodes=None, seed=None, **kwargs):
    """The reference rows of every results table on ``task``: ``{"random": Score, "stalest":
    ..., "greedy": ..., "planner": ...}``, evaluated as :func:`evaluate` evaluates (the
    planner, a search that knows the world, is the measure of what is achievable). Cached per
    config, task, episodes and seed for the process."""
    env = task_env(task, **kwargs)
    episodes, seed = _episodes_and_seed(env, episodes, seed, exact)
    info = env.task_of(0)
    key = (env.config_toml, info["lam"], info["rain"], info["rain_moves_every"], exact, episodes, seed)
    if key not in _REFERENCE_CACHE:
        _REFERENCE_CACHE[key] = {
            name: evaluate(name, env, exact=exact, episodes=episodes, seed=seed, trapped=False)
            for name in REFERENCES
        }
    return dict(_REFERENCE_CACHE[key])


def normalised_score(score, task=None, **kwargs):
    """``100 * (R - R_random) / (R_planner - R_random)`` of a return R (a number or a
    :class:`Score`) on ``task``: 0 is the random policy, 100 the planner reference, each
    evaluated by :func:`references` with ``kwargs`` (``exact``, ``episodes``, ``seed`` and the
    task's arguments). A :class:`Score` brings its own ``exact`` and ``seed``."""
    if isinstance(score, Score):
        kwargs.setdefault("exact", score.exact)
        kwargs.setdefault("seed", score.seed)
        if not score.exact:
            kwargs.setdefault("episodes", score.num_episodes)
        ret = score.ret.mean
    elif isinstance(score, numbers.Real) and not isinstance(score, bool):
        ret = float(score)
    else:
        raise TypeError(f"score = {score!r}: expected a return or a uavmeta.Score")
    refs = references(task, **kwargs)
    low, high = refs["random"].ret.mean, refs["planner"].ret.mean
    return 100.0 * (ret - low) / (high - low)
