"""``SB3VecEnv``: a :class:`uavmeta.VectorEnv` as Stable-Baselines3's ``VecEnv``, so SB3's
algorithms (PPO, A2C, DQN, ...) step all sub-envs in one Rust call.

SB3 resets a sub-env in the step that ends its episode (its ``VecEnv`` contract) where
Gymnasium 1.x resets it in the next step: the adapter starts the next episode of each env that
reached the horizon at once, returns its first observation, and puts the last one in
``infos[i]["terminal_observation"]`` with ``infos[i]["TimeLimit.truncated"] = True`` (the
horizon is a time limit, so SB3 bootstraps through it). Episodes, seeds and tasks are the
``VectorEnv``'s: ``seed(S)`` then ``reset()`` seeds env i with S + i, as SB3's ``DummyVecEnv``
of ``UavEnv``\\ s, step for step.

    from stable_baselines3 import PPO
    venv = uavmeta.sb3.SB3VecEnv(uavmeta.VectorEnv(64, lam=300.0, normalised=True))
    PPO("MlpPolicy", venv).learn(10_000)

Needs stable-baselines3 (``pip install "uavmeta[sb3]"``).
"""

import numpy as np
from stable_baselines3.common.vec_env import VecEnv

from .vector import VectorEnv
from .env import task_info


class SB3VecEnv(VecEnv):
    """``venv`` (a :class:`uavmeta.VectorEnv`) behind SB3's ``VecEnv`` interface."""

    def __init__(self, venv):
        venv = getattr(venv, "unwrapped", venv)
        if not isinstance(venv, VectorEnv):
            raise TypeError(f"venv = {venv!r}: expected a uavmeta.VectorEnv")
        self.venv = venv
        self.render_mode = venv.render_mode
        super().__init__(venv.num_envs, venv.single_observation_space, venv.single_action_space)
        self._actions = None

    def reset(self):
        seeds = self._seeds
        seed = None if all(s is None for s in seeds) else list(seeds)
        obs, info = self.venv.reset(seed=seed)
        self._reset_seeds()
        self.reset_infos = _per_env(info, self.num_envs)
        return obs

    def step_async(self, actions):
        self._actions = actions

    def step_wait(self):
        actions = np.asarray(self._actions).reshape(self.num_envs)
        obs, reward, terminated, truncated, info = self.venv.step(actions)
        done = terminated | truncated
        infos = _per_env(info, self.num_envs)
        worlds = self.venv._worlds
        timeouts = (truncated & ~terminated).tolist()
        for i in range(self.num_envs):  # as DummyVecEnv: every env's info says it
            infos[i]["TimeLimit.truncated"] = timeouts[i]
        for i in np.flatnonzero(done):
            infos[i]["terminal_observation"] = obs[i].copy()
            obs[i] = worlds.reset_one(int(i))  # the next episode, as the autoreset would start
            self.reset_infos[i] = task_info(worlds, int(i))
        return obs, reward.astype(np.float32), done, infos

    def close(self):
        self.venv.close()

    def get_images(self):
        return list(self.venv.render())

    def get_attr(self, attr_name, indices=None):
        return [getattr(self.venv, attr_name) for _ in self._get_indices(indices)]

    def set_attr(self, attr_name, value, indices=None):
        raise AttributeError(
            f"set_attr({attr_name!r}): the sub-envs of a uavmeta.VectorEnv share their settings"
        )

    def env_method(self, method_name, *method_args, indices=None, **method_kwargs):
        if method_name == "task_of":
            return [self.venv.task_of(i) for i in self._get_indices(indices)]
        method = getattr(self.venv, method_name)
        return [method(*method_args, **method_kwargs) for _ in self._get_indices(indices)]

    def env_is_wrapped(self, wrapper_class, indices=None):
        return [False for _ in self._get_indices(indices)]


def _per_env(info, n):
    """Gymnasium's dict of arrays (with ``_key`` masks) as SB3's list of one dict per env."""
    out = [{} for _ in range(n)]
    for key, values in info.items():
        if key.startswith("_"):
            continue
        mask = info.get("_" + key, np.ones(n, bool))
        for i in np.flatnonzero(mask):
            out[i][key] = values[i].item() if hasattr(values[i], "item") else values[i]
    return out
