"""``UavTeamEnv``: one world of a UAV team (``world.uavs``, docs/MODEL.md section 11) as a
PettingZoo ``ParallelEnv``, stepped in Rust.

```python
from uavmeta.pettingzoo import parallel_env
env = parallel_env(uavs=2, step_cells=2, idle_action=True, lam=300.0)
observations, infos = env.reset(seed=0)
while env.agents:
    actions = {agent: env.action_space(agent).sample() for agent in env.agents}
    observations, rewards, terminations, truncations, infos = env.step(actions)
```
"""

import numpy as np
from gymnasium import spaces
from pettingzoo import ParallelEnv

from . import _args
from . import render as _render
from ._uavmeta import Worlds
from .env import (
    ResetNeeded,
    WorldProperties,
    action_index,
    episode_seeds,
    observation_space,
    task_info,
)
from .team import state_space


class UavTeamEnv(WorldProperties, ParallelEnv):
    """The world of U UAVs over one set of K devices, one agent a UAV (``uav_0`` ..).

    - Agent u's observation: ``Box`` of 2 + K float32 values, [x_u, y_u, A_1..A_K], its own
      cell and the shared AoI (raw; ``normalised=True`` divides as the networks see them).
    - Agent u's action: ``Discrete(5 * targets)``, ``a = move * targets + target``, the
      targets the K devices and, with ``idle_action=True``, "none" (target K).
    - Reward: the team's, the same for every agent: -(sum_j delta_j A_j + lambda / K * the
      team's power + the risky region's penalties).
    - ``state()``: the global state, every UAV's cell then the AoI (``state_space``).
    - Every agent is truncated together at the horizon T; no agent terminates.
    - ``infos[agent]``: ``aoi``, ``power_mw`` (the team's), ``outages`` (the team's),
      ``target`` (the agent's device, K for none), ``task_id`` and ``lam``.

    Takes :class:`uavmeta.UavEnv`'s task and world arguments (``uavs``, ``step_cells``,
    ``idle_action`` and any other ``world.*`` key, or a config that sets them) and its seeds:
    ``reset(seed=S)`` starts episode 0 of S, a later ``reset()`` the next episode, the episodes
    ``uavmeta env rollout --seed S`` flies.
    """

    metadata = {"name": "uavmeta_team_v0", "render_modes": ["rgb_array"], "render_fps": 4}

    def __init__(self, *, config=None, task=None, lam=None, rain=None, rain_moves_every=None,
                 normalised=False, render_mode=None, set=None, tasks=None, **world):
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode = {render_mode!r}: expected 'rgb_array' or None")
        self._worlds = Worlds(
            1,
            **_args.native_kwargs(
                config, task, lam, rain, rain_moves_every, normalised, set, world, tasks
            ),
        )
        self.render_mode = render_mode
        self.possible_agents = [f"uav_{u}" for u in range(self._worlds.uavs)]
        self.agents = []
        self._observation_space = observation_space(self._worlds)
        self._action_space = spaces.Discrete(self._worlds.action_count)
        self.observation_spaces = {a: self._observation_space for a in self.possible_agents}
        self.action_spaces = {a: self._action_space for a in self.possible_agents}
        self.state_space = state_space(self._worlds)
        self._state = None
        self._paths = []
        self._rng = np.random.default_rng()

    def observation_space(self, agent):
        self._check_agent(agent)
        return self._observation_space

    def action_space(self, agent):
        self._check_agent(agent)
        return self._action_space

    def _check_agent(self, agent):
        if agent not in self.observation_spaces:
            raise KeyError(f"agent {agent!r}: expected one of {', '.join(self.possible_agents)}")

    def reset(self, seed=None, options=None):
        fresh = lambda n: self._rng.integers(2**63, size=n)  # noqa: E731
        seed = None if seed is None else _args.seed(seed)  # one int: no list, unlike a vector env
        seeds = episode_seeds(seed, 1, self._state is not None, fresh)
        obs, state = self._worlds.reset_team(seeds)
        self.agents = list(self.possible_agents)
        self._state = state[0]
        self._paths = [[cell] for cell in self._worlds.uav_cells(0)]
        info = task_info(self._worlds, 0)
        return self._per_agent(obs[0]), {a: dict(info) for a in self.agents}

    def step(self, actions):
        if not self.agents:
            raise ResetNeeded("step() with no agents left: call reset() first")
        if not isinstance(actions, dict):
            raise TypeError(f"actions = {actions!r}: expected a dict of one action per agent")
        unknown = [a for a in actions if a not in self.agents]
        if unknown:
            raise ValueError(f"actions for {unknown[0]!r}: expected only the agents {self.agents}")
        missing = [a for a in self.agents if a not in actions]
        if missing:
            raise ValueError(f"actions lack {missing[0]!r}: expected one action per agent")
        count = self._action_space.n
        row = [action_index(actions[a], count) for a in self.possible_agents]
        (obs, state, reward, truncated, aoi, power_mw, outages, targets, _stepped, _task_id,
         _lam, _layout) = self._worlds.step_team(np.array([row], dtype=np.int64))
        self._state = state[0]
        for path, cell in zip(self._paths, self._worlds.uav_cells(0)):
            path.append(cell)
        agents, done = self.agents, bool(truncated[0])
        info = dict(aoi=float(aoi[0]), power_mw=float(power_mw[0]), outages=int(outages[0]),
                    **task_info(self._worlds, 0))
        infos = {a: dict(info, target=int(targets[0, u])) for u, a in enumerate(agents)}
        rewards = {a: float(reward[0]) for a in agents}
        self.agents = [] if done else agents
        return (self._per_agent(obs[0]), rewards, {a: False for a in agents},
                {a: done for a in agents}, infos)

    def _per_agent(self, obs):
        return {a: obs[u] for u, a in enumerate(self.possible_agents)}

    def state(self):
        """The global state, every UAV's cell (UAV 0 first) then the devices' AoI."""
        if self._state is None:
            raise ResetNeeded("state() before reset(): call reset() first")
        return self._state.copy()

    def render(self):
        """An RGB array (H, W, 3): the grid, the rain, the devices by AoI, every UAV and its
        path so far."""
        if self.render_mode is None:
            return None
        return _render.frame(self._worlds, 0, trajectories=self._paths)

    def close(self):
        pass


def parallel_env(**kwargs):
    """A :class:`UavTeamEnv` of the task and world ``kwargs`` name, as PettingZoo's
    ``parallel_env`` factories make their envs."""
    return UavTeamEnv(**kwargs)
