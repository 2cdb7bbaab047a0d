"""The heuristic behaviour policies as batched functions of observations.

Each is built for an env (a ``UavEnv``, a ``VectorEnv`` or a ``gymnasium.make`` of them), whose
task it knows (device cells, deltas, powers, the configured rain zone), and maps observations as
that env returns them (raw or normalised), one (2 + K,) row or an (N, 2 + K) batch, to action
indices. They are the Rust policies of ``uavmeta env rollout --policy NAME``, so both choose the
same actions:

- ``random(env, seed)``: uniform over the 5K actions, one draw per row from a stream seeded by
  ``seed`` (the CLI's ``--seed``);
- ``stalest(env)``: serve the device with the largest delta_k A_k, fly towards it;
- ``greedy(env)``: serve the device that makes this step cheapest, fly towards the stalest;
- ``planner(env)``: the planner reference (SPEC section 5), a search that knows the world, the
  measure of what is achievable. Call it with the step ``t`` the observations are at
  (``policy(obs, t=env.t)``): it plans the remaining T - t steps from each row, exactly where the
  rain does not move (with the task's configured zone where it does). It keeps its plan while
  the observations follow it, so an episode stepped one observation at a time plans once.
"""

import numpy as np

from ._uavmeta import Heuristic as _Heuristic

NAMES = ("random", "stalest", "greedy", "planner")


class HeuristicPolicy:
    """``policy(obs)``: an action index for one observation, an int64 array for a batch."""

    def __init__(self, name, env, seed=0):
        worlds = _worlds_of(env)
        self.name = name
        self._native = _Heuristic(name, worlds, normalised=worlds.normalised, seed=seed)

    def __call__(self, obs, t=0):
        obs = np.asarray(obs, dtype=np.float32)
        if obs.ndim not in (1, 2):
            raise ValueError(
                f"observations of shape {obs.shape}: expected (2 + K,) or (N, 2 + K)"
            )
        actions = self._native(np.ascontiguousarray(np.atleast_2d(obs)), t=t)
        return int(actions[0]) if obs.ndim == 1 else actions

    def __repr__(self):
        return f"HeuristicPolicy({self.name!r})"


def random(env, seed=0):
    return HeuristicPolicy("random", env, seed)


def stalest(env):
    return HeuristicPolicy("stalest", env)


def greedy(env):
    return HeuristicPolicy("greedy", env)


def planner(env):
    return HeuristicPolicy("planner", env)


def make(name, env, seed=0):
    """The policy called ``name`` (one of :data:`NAMES`) for ``env``."""
    if name not in NAMES:
        raise ValueError(f"policy = {name!r}: expected one of {', '.join(NAMES)}")
    return HeuristicPolicy(name, env, seed)


def _worlds_of(env):
    for e in (env, getattr(env, "unwrapped", None)):
        worlds = getattr(e, "_worlds", None)
        if worlds is not None:
            return worlds
    raise ValueError(f"env = {env!r}: expected a uavmeta UavEnv or VectorEnv")
