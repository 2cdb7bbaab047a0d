"""``VectorEnv``: N worlds stepped in Rust in one call, each of its own task or all of one,
Gymnasium's ``VectorEnv``."""

import numpy as np
from gymnasium.vector import VectorEnv as _GymVectorEnv
from gymnasium.vector.utils import batch_space
from gymnasium import spaces

from . import _args
from ._uavmeta import Worlds
from . import render as _render
from .env import ResetNeeded, WorldProperties, episode_seeds, observation_space, one_uav

try:  # Gymnasium >= 1.1 names the autoreset modes.
    from gymnasium.vector import AutoresetMode

    _NEXT_STEP = AutoresetMode.NEXT_STEP
except ImportError:  # Gymnasium 1.0: next-step autoreset is the only mode.
    _NEXT_STEP = "NextStep"


class VectorEnv(WorldProperties, _GymVectorEnv):
    """``num_envs`` worlds, stepped together by the Rust world with the GIL released: no
    Python per env or per step of an env.

    Takes the same task and world arguments as :class:`uavmeta.UavEnv`, and behaves exactly as
    ``gymnasium.vector.SyncVectorEnv`` of ``num_envs`` such envs: ``reset(seed=S)`` seeds env i
    with S + i (or with ``seed[i]`` given a list), and autoreset is Gymnasium 1.x's next-step
    mode: the step after env i is truncated ignores its action, resets it and returns its first
    observation with reward 0. ``infos`` has ``aoi``, ``power_mw``, ``outage`` and ``device``
    with the masks ``_aoi``, ... that say which envs stepped, and every env's ``task_id`` and
    ``lam`` (``reset``'s infos too), and ``layout_id`` where tasks have device layouts of
    their own.

    A task per sub-env: ``tasks=[...]`` gives env i the task ``tasks[i % len(tasks)]`` (a
    task name of the config, a lambda, or a dict of ``task`` or ``lam``, ``rain``,
    ``rain_moves_every`` and ``layout``: a ``world.layout_seed`` or one (x, y) cell per device,
    so tasks differ in where the devices are); ``tasks=uavmeta.TaskSampler(...)`` draws env i a
    new task at each of its resets.
    ``task_of(i)`` says which task env i runs now.

    Returned arrays are new each step: observations (N, 2 + K) float32, rewards float64.
    ``step`` before ``reset`` raises ``uavmeta.ResetNeeded``.
    """

    metadata = {"autoreset_mode": _NEXT_STEP, "render_modes": ["rgb_array"], "render_fps": 4}

    def __init__(
        self,
        num_envs,
        *,
        config=None,
        task=None,
        lam=None,
        rain=None,
        rain_moves_every=None,
        normalised=False,
        render_mode=None,
        set=None,
        tasks=None,
        **world,
    ):
        num_envs = _args.natural("num_envs", num_envs, upper=2**64)
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode = {render_mode!r}: expected 'rgb_array' or None")
        self._worlds = Worlds(
            num_envs,
            **_args.native_kwargs(
                config, task, lam, rain, rain_moves_every, normalised, set, world, tasks
            ),
        )
        self.num_envs = num_envs
        self.render_mode = render_mode
        self.single_observation_space = observation_space(self._worlds)
        one_uav(self._worlds, "VectorEnv")
        self.single_action_space = spaces.Discrete(self._worlds.action_count)
        self.observation_space = batch_space(self.single_observation_space, num_envs)
        self.action_space = batch_space(self.single_action_space, num_envs)
        self._started = False

    @classmethod
    def from_config(cls, num_envs, path, task=None, **kwargs):
        return cls(num_envs, config=path, task=task, **kwargs)

    def reset(self, *, seed=None, options=None):
        seeds = episode_seeds(seed, self.num_envs, self._started, self._fresh_seeds)
        if seed is not None or self._started:
            super().reset(seed=seeds[0])
        self._started = True
        obs = self._worlds.reset(seeds)
        return obs, self._task_infos(*self._worlds.task_arrays())

    def _fresh_seeds(self, n):
        """As SyncVectorEnv's unseeded sub-envs on a first reset: seeds from fresh entropy."""
        super().reset()
        return self.np_random.integers(2**63, size=n)

    def _task_infos(self, task_id, lam, layout):
        every = getattr(self, "_every", None)
        if every is None:  # one read-only mask of all envs, shared by every step's infos
            every = self._every = np.ones(self.num_envs, dtype=bool)
            every.flags.writeable = False
        infos = {"task_id": task_id, "_task_id": every, "lam": lam, "_lam": every}
        if self._worlds.layout_count > 1:
            infos.update(layout_id=layout, _layout_id=every)
        return infos

    def step(self, actions):
        actions = check_actions(actions, self.num_envs, self.single_action_space.n)
        if not self._started:
            raise ResetNeeded("step() before reset(): call reset() first")
        (obs, reward, terminated, truncated, aoi, power_mw, outage, device, stepped, task_id,
         lam, layout) = self._worlds.step(actions)
        infos = {}
        if stepped.any():
            infos = {
                "aoi": aoi,
                "_aoi": stepped,
                "power_mw": power_mw,
                "_power_mw": stepped,
                "outage": outage,
                "_outage": stepped,
                "device": device,
                "_device": stepped,
            }
        infos.update(self._task_infos(task_id, lam, layout))
        return obs, reward, terminated, truncated, infos

    @property
    def tasks(self):
        """Every sub-env's task now (``task_of(i)`` for each i)."""
        return [self.task_of(i) for i in range(self.num_envs)]

    def render(self):
        """One RGB array per env, as ``UavEnv.render`` draws it (without the path)."""
        return tuple(_render.frame(self._worlds, i) for i in range(self.num_envs))


def check_actions(actions, num_envs, count):
    """``actions`` as a contiguous int64 array of one action index per env: a TypeError naming
    them if they are no integers, a ValueError naming the first out of range (by its own value,
    before any cast; Rust checks the rest)."""
    actions = np.asarray(actions)
    if actions.dtype.kind not in "iu":
        raise TypeError(f"actions of dtype {actions.dtype}: expected integer action indices")
    if actions.shape != (num_envs,):
        raise ValueError(f"actions of shape {actions.shape}: expected ({num_envs},), one per env")
    # Every signed and small unsigned value survives the cast, and Rust names any out of range;
    # a uint64 above int64's range would wrap, so it is named here by its own value.
    if actions.dtype == np.uint64 and num_envs and actions.max() >= count:
        i = int(np.argmax(actions >= count))
        raise ValueError(
            f"actions[{i}] = {int(actions[i])}: expected an action index in 0..{count} "
            f"(a = move * K + device)"
        )
    return np.ascontiguousarray(actions, dtype=np.int64)
