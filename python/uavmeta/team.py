"""``TeamVectorEnv``: N worlds of a UAV team (``world.uavs``, docs/MODEL.md section 11) stepped
in Rust in one call, and the spaces of one UAV and of the team's state."""

import numpy as np
from gymnasium import spaces

from . import _args
from ._uavmeta import Worlds
from .env import ResetNeeded, WorldProperties, episode_seeds, observation_space


def state_space(worlds):
    """Box of the team's state, 2U + K float32 values: every UAV's cell, UAV 0 first, then the
    devices' AoI (divided by L-1, L-1, ..., aoi_max when the worlds are normalised)."""
    one = observation_space(worlds)
    cells = np.tile(one.low[:2], worlds.uavs), np.tile(one.high[:2], worlds.uavs)
    low = np.concatenate([cells[0], one.low[2:]])
    high = np.concatenate([cells[1], one.high[2:]])
    return spaces.Box(low, high, dtype=np.float32)


def check_team_actions(actions, num_envs, uavs, count):
    """``actions`` as a contiguous (num_envs, uavs) int64 array: a TypeError if they are no
    integers, a ValueError naming the first out of range by its own value (Rust names the rest)."""
    actions = np.asarray(actions)
    if actions.dtype.kind not in "iu":
        raise TypeError(f"actions of dtype {actions.dtype}: expected integer action indices")
    if actions.shape != (num_envs, uavs):
        raise ValueError(
            f"actions of shape {actions.shape}: expected ({num_envs}, {uavs}), one per env and UAV"
        )
    if actions.dtype == np.uint64 and actions.size and actions.max() >= count:
        i, u = np.argwhere(actions >= count)[0]
        raise ValueError(
            f"actions[{i}, {u}] = {int(actions[i, u])}: expected an action index in 0..{count}"
        )
    return np.ascontiguousarray(actions, dtype=np.int64)


class TeamVectorEnv(WorldProperties):
    """``num_envs`` worlds of U UAVs each, stepped together by the Rust world with the GIL
    released: the batched form of :class:`uavmeta.pettingzoo.UavTeamEnv`.

    Takes :class:`uavmeta.VectorEnv`'s arguments (``uavs=2``, ``step_cells=2``,
    ``idle_action=True`` and any other ``world.*`` key as keywords, or a config that sets them)
    and its seeds and next-step autoreset. ``reset`` returns each UAV's observation,
    (N, U, 2 + K) float32, and infos; ``step(actions)`` takes an (N, U) array of action indices
    (``a = move * targets + target``, target K "none" with ``idle_action``) and returns
    ``(obs, reward, terminated, truncated, infos)`` with the team's reward (N,). ``infos`` has
    ``state`` (N, 2U + K), the team's state, always, and after a step ``aoi``, ``power_mw``,
    ``outages`` (UAVs in rain this step) and ``targets`` (N, U; K for none), each with its mask
    (``_aoi``, ...) of the envs that stepped, plus ``task_id`` and ``lam``.
    """

    def __init__(self, num_envs, *, config=None, task=None, lam=None, rain=None,
                 rain_moves_every=None, normalised=False, set=None, tasks=None, **world):
        num_envs = _args.natural("num_envs", num_envs, upper=2**64)
        self._worlds = Worlds(
            num_envs,
            **_args.native_kwargs(
                config, task, lam, rain, rain_moves_every, normalised, set, world, tasks
            ),
        )
        self.num_envs, self.uavs = num_envs, self._worlds.uavs
        self.single_observation_space = observation_space(self._worlds)
        self.single_action_space = spaces.Discrete(self._worlds.action_count)
        self.state_space = state_space(self._worlds)
        # Seeds of a first reset without one: fresh entropy, as Gymnasium draws them.
        self._rng = np.random.default_rng()
        self._started = False

    def reset(self, *, seed=None, options=None):
        fresh = lambda n: self._rng.integers(2**63, size=n)  # noqa: E731
        seeds = episode_seeds(seed, self.num_envs, self._started, fresh)
        self._started = True
        obs, state = self._worlds.reset_team(seeds)
        task_id, lam, _ = self._worlds.task_arrays()
        return obs, {"state": state, "task_id": task_id, "lam": lam}

    def step(self, actions):
        actions = check_team_actions(actions, self.num_envs, self.uavs,
                                     self.single_action_space.n)
        if not self._started:
            raise ResetNeeded("step() before reset(): call reset() first")
        (obs, state, reward, truncated, aoi, power_mw, outages, targets, stepped, task_id, lam,
         _layout) = self._worlds.step_team(actions)
        terminated = np.zeros(self.num_envs, dtype=bool)
        infos = {"state": state, "task_id": task_id, "lam": lam}
        if stepped.any():
            for key, value in (("aoi", aoi), ("power_mw", power_mw), ("outages", outages),
                               ("targets", targets)):
                infos[key], infos["_" + key] = value, stepped
        return obs, reward, terminated, truncated, infos

    def uav_cells(self, i=0):
        """Every UAV's cell in env ``i``, UAV 0 first."""
        return self._worlds.uav_cells(i)
