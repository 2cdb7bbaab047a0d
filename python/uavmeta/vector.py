"""``VectorEnv``: N worlds of one task stepped in Rust in one call, Gymnasium's ``VectorEnv``."""

import numpy as np
from gymnasium.vector import VectorEnv as _GymVectorEnv
from gymnasium.vector.utils import batch_space
from gymnasium import spaces

from . import _args
from ._uavmeta import Worlds
from . import render as _render
from .env import WorldProperties, observation_space

try:  # Gymnasium >= 1.1 names the autoreset modes.
    from gymnasium.vector import AutoresetMode

    _NEXT_STEP = AutoresetMode.NEXT_STEP
except ImportError:  # Gymnasium 1.0: next-step autoreset is the only mode.
    _NEXT_STEP = "NextStep"


class VectorEnv(WorldProperties, _GymVectorEnv):
    """``num_envs`` worlds of one task, stepped together by the Rust world with the GIL
    released: no Python per env or per step of an env.

    Takes the same task and world arguments as :class:`uavmeta.UavEnv`, and behaves exactly as
    ``gymnasium.vector.SyncVectorEnv`` of ``num_envs`` such envs: ``reset(seed=S)`` seeds env i
    with S + i (or with ``seed[i]`` given a list), and autoreset is Gymnasium 1.x's next-step
    mode: the step after env i is truncated ignores its action, resets it and returns its first
    observation with reward 0. ``infos`` has ``aoi``, ``power_mw``, ``outage`` and ``device``
    with the masks ``_aoi``, ... that say which envs stepped (none when every env reset).

    Returned arrays are new each step: observations (N, 2 + K) float32, rewards float64.
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
        **world,
    ):
        num_envs = _args.natural("num_envs", num_envs)
        self._worlds = Worlds(
            num_envs,
            **_args.native_kwargs(
                config, task, lam, rain, rain_moves_every, normalised, set, world
            ),
        )
        self.num_envs = num_envs
        self.render_mode = render_mode
        self.single_observation_space = observation_space(self._worlds)
        self.single_action_space = spaces.Discrete(5 * self._worlds.devices)
        self.observation_space = batch_space(self.single_observation_space, num_envs)
        self.action_space = batch_space(self.single_action_space, num_envs)
        self._started = False

    @classmethod
    def from_config(cls, num_envs, path, task=None, **kwargs):
        return cls(num_envs, config=path, task=task, **kwargs)

    def reset(self, *, seed=None, options=None):
        n = self.num_envs
        if seed is None:
            super().reset()
            # As SyncVectorEnv's unseeded sub-envs: each goes on to its next episode, or, on the
            # first reset, starts from fresh entropy.
            seeds = [None] * n
            if not self._started:
                seeds = [int(s) for s in self.np_random.integers(2**63, size=n)]
        elif isinstance(seed, (list, tuple, np.ndarray)):
            if len(seed) != n:
                raise ValueError(
                    f"seed has {len(seed)} entries: expected one per env, num_envs = {n}"
                )
            seeds = [_args.seed(s, f"seed[{i}]") for i, s in enumerate(seed)]
            super().reset(seed=seeds[0])
        else:
            base = _args.seed(seed)
            seeds = [_args.seed(base + i, f"seed + {i}") for i in range(n)]
            super().reset(seed=base)
        self._started = True
        return self._worlds.reset(seeds), {}

    def step(self, actions):
        actions = np.asarray(actions)
        if actions.dtype.kind not in "iu":
            raise ValueError(
                f"actions of dtype {actions.dtype}: expected integer action indices"
            )
        if actions.shape != (self.num_envs,):
            raise ValueError(
                f"actions of shape {actions.shape}: expected ({self.num_envs},), one per env"
            )
        actions = np.ascontiguousarray(actions, dtype=np.int64)
        obs, reward, terminated, truncated, aoi, power_mw, outage, device, stepped = (
            self._worlds.step(actions)
        )
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
        return obs, reward, terminated, truncated, infos

    def render(self):
        """One RGB array per env, as ``UavEnv.render`` draws it (without the path)."""
        return tuple(_render.frame(self._worlds, i) for i in range(self.num_envs))
