"""``UavEnv``: one world of one task as a ``gymnasium.Env``."""

import operator

import gymnasium
import numpy as np
from gymnasium import spaces

from . import _args
from ._uavmeta import Worlds
from . import render as _render


def observation_space(worlds):
    """Box of 2 + K float32 values: raw [x, y, A_1..A_K] (x, y in 0..L-1, A in 1..aoi_max), or
    each divided by L-1, L-1, aoi_max when the worlds are normalised."""
    last = float(worlds.grid_cells - 1)
    k = worlds.devices
    low = np.array([0.0, 0.0] + [1.0] * k, dtype=np.float32)
    high = np.array([last, last] + [float(worlds.aoi_max)] * k, dtype=np.float32)
    if worlds.normalised:
        scale = np.array(worlds.observation_scale, dtype=np.float32)
        low, high = low / scale, high / scale
    return spaces.Box(low, high, dtype=np.float32)


def one_uav(worlds, name):
    """A ValueError unless ``worlds`` fly one UAV: a team has an env of its own."""
    if worlds.uavs != 1:
        raise ValueError(
            f"world.uavs = {worlds.uavs}: {name} flies one UAV; a team's env is "
            "uavmeta.pettingzoo.parallel_env(uavs=...) or uavmeta.TeamVectorEnv(n, uavs=...)"
        )


def episode_seeds(seed, n, started, fresh):
    """The native seeds of a reset of ``n`` envs, as ``SyncVectorEnv`` seeds its sub-envs:
    S + i for a seed S, ``seed[i]`` for a list (None: that env's next episode), and without a
    seed each env's next episode, or ``fresh()`` draws on the first reset."""
    if seed is None:
        return [int(s) for s in fresh(n)] if not started else [None] * n
    if isinstance(seed, (list, tuple, np.ndarray)):
        if len(seed) != n:
            raise ValueError(f"seed has {len(seed)} entries: expected one per env, num_envs = {n}")
        seeds = [None if s is None else _args.seed(s, f"seed[{i}]") for i, s in enumerate(seed)]
        if not started and None in seeds:
            raise ValueError(
                f"seed = {seed!r}: the first reset needs a seed for every env (or seed=None)"
            )
        return seeds
    base = _args.seed(seed)
    return [_args.seed(base + i, f"seed + {i}") for i in range(n)]


class ResetNeeded(gymnasium.error.ResetNeeded, RuntimeError):
    """``step`` before the first ``reset`` (or after the episode ended, for ``UavEnv``)."""


def action_index(action, count):
    """An action as a Python int: a TypeError naming it if it is no integer, a ValueError if it
    is out of range."""
    if isinstance(action, (bool, np.bool_)):
        raise TypeError(f"action = {action!r}: expected an integer action index in 0..{count}")
    try:
        a = operator.index(action)
    except TypeError:
        raise TypeError(
            f"action = {action!r}: expected an integer action index in 0..{count}"
        ) from None
    if not 0 <= a < count:
        raise ValueError(
            f"action = {action!r}: expected an action index in 0..{count} "
            f"(a = move * K + device)"
        )
    return a


def task_info(worlds, i):
    """The ``info`` keys of env ``i``'s task: ``task_id``, ``lam``, and ``layout_id`` where the
    tasks have device layouts of their own."""
    task_id, lam, _, _, _, layout = worlds.task_now(i)
    info = {"task_id": task_id, "lam": lam}
    if worlds.layout_count > 1:
        info["layout_id"] = layout
    return info


class WorldProperties:
    """What the task's world is, for drawing, policies and users; ``_worlds`` is the native
    ``Worlds``."""

    @property
    def device_cells(self):
        return self._worlds.device_cells(0)

    @property
    def devices(self):
        return self._worlds.devices

    @property
    def grid_cells(self):
        return self._worlds.grid_cells

    @property
    def horizon(self):
        return self._worlds.horizon

    @property
    def lam(self):
        return self._worlds.lam

    @property
    def task_name(self):
        return self._worlds.task_name

    @property
    def config_toml(self):
        """The whole config the env was built from, every key written out."""
        return self._worlds.config_toml

    def task_of(self, i=0):
        """Sub-env ``i``'s task now, as a dict: ``task_id``, ``lam``, ``rain`` (x0, y0, x1, y1)
        or None, ``rain_moves_every`` or None, ``name`` (the config's, or the one-off name
        ``uavmeta env rollout --lambda ... --rain ...`` gives it), ``layout_id`` (its device
        layout's index, 0 for the config's) and ``device_cells``. ``uavmeta.evaluate`` takes
        this dict as its task."""
        task_id, lam, rain, moves, name, layout = self._worlds.task_now(i)
        cells = self._worlds.device_cells(i)
        return dict(task_id=task_id, lam=lam, rain=rain, rain_moves_every=moves, name=name,
                    layout_id=layout, device_cells=cells)


class UavEnv(WorldProperties, gymnasium.Env):
    """The UAV world of one task (docs/MODEL.md sections 1-3), stepped in Rust.

    - Observation: ``Box`` of 2 + K float32 values, **raw** by default: [x_u, y_u, A_1..A_K]
      with the cell in 0..L-1 and every AoI in 1..aoi_max. ``normalised=True`` divides them by
      L-1, L-1 and aoi_max, as the project's networks see them.
    - Action: ``Discrete(5K)``, ``a = move * K + device``, moves in ``uavmeta.MOVES`` order
      (north, south, east, west, hover).
    - Reward: r(t) = -(sum_j delta_j A_j + lambda / K * P_mW).
    - ``terminated`` is always False; ``truncated`` is True at the horizon T.
    - ``info``: ``aoi`` (mean AoI over the devices after the step), ``power_mw`` (the power
      spent), ``outage`` (the UAV was in rain) and ``device`` (the served device).

    The task: ``config`` (a TOML file; the defaults when absent) and ``task`` (a task name
    in it), or a one-off ``lam`` with optional ``rain`` = (x0, y0, x1, y1) and
    ``rain_moves_every``; with neither, lambda = 300; or ``tasks=uavmeta.TaskSampler(...)``,
    a new task at every reset. ``info`` (of ``reset`` too) then has the task's ``task_id``
    and ``lam``. Any other keyword is a ``world.*`` key (``horizon=20``, ``devices=5``,
    ``start_cell=[0, 0]``, ...), and ``set`` takes a list of raw ``KEY=VALUE`` overrides as
    the CLI's ``--set``. Bad arguments raise ``TypeError`` (a wrong type) or ``ValueError``
    (a wrong value), naming the argument; a missing ``config`` file ``FileNotFoundError``.
    ``step`` before ``reset`` raises ``uavmeta.ResetNeeded``.

    An env pickles and deep-copies with its state: the copy stands at the same step of the
    same episode and steps on exactly as the original.

    Seeds: ``reset(seed=S)`` starts episode 0 of S and each later ``reset()`` the next
    episode, the episodes ``uavmeta env rollout --seed S`` runs. As Gymnasium specifies, a
    first ``reset()`` without a seed draws one from fresh entropy: pass a seed to reproduce.
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 4}

    def __init__(
        self,
        *,
        config=None,
        task=None,
        lam=None,
        rain=None,
        rain_moves_every=None,
        normalised=False,
        render_mode="rgb_array",
        set=None,
        tasks=None,
        **world,
    ):
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode = {render_mode!r}: expected 'rgb_array' or None")
        from .tasks import TaskSampler

        if tasks is not None and not isinstance(tasks, TaskSampler):
            raise TypeError(
                f"tasks = {tasks!r}: expected a uavmeta.TaskSampler (a list of tasks, one per "
                "sub-env, is for VectorEnv)"
            )
        self._init_kwargs = dict(
            config=config, task=task, lam=lam, rain=rain, rain_moves_every=rain_moves_every,
            normalised=normalised, render_mode=render_mode, set=set, tasks=tasks, **world,
        )
        self._worlds = Worlds(
            1,
            **_args.native_kwargs(
                config, task, lam, rain, rain_moves_every, normalised, set, world, tasks
            ),
        )
        self.render_mode = render_mode
        one_uav(self._worlds, "UavEnv")
        self.observation_space = observation_space(self._worlds)
        self.action_space = spaces.Discrete(self._worlds.action_count)
        self._started = False
        self._cells = []
        self._actions = []

    def __getstate__(self):
        """The constructor's arguments, where the env stands (its seed, episode and the actions
        of the episode so far) and its Gymnasium random stream; no native object."""
        seed, episode = self._worlds.seed_and_episode(0)
        return dict(
            init=self._init_kwargs,
            started=self._started,
            seed=seed,
            episode=episode,
            actions=list(self._actions),
            np_random=self._np_random if getattr(self, "_np_random", None) is not None else None,
            np_random_seed=getattr(self, "_np_random_seed", None),
        )

    def __setstate__(self, state):
        self.__init__(**state["init"])
        self._np_random = state["np_random"]
        if state["np_random_seed"] is not None:
            self._np_random_seed = state["np_random_seed"]
        if state["started"]:
            # The world is deterministic given its seed, episode and actions: replay them.
            self._worlds.reset_to(0, state["seed"], state["episode"])
            self._started = True
            self._cells = [self.uav]
            for a in state["actions"]:
                self._step(a)

    @classmethod
    def from_config(cls, path, task=None, **kwargs):
        """The env of task ``task`` of the config file ``path`` (or a one-off ``lam=``)."""
        return cls(config=path, task=task, **kwargs)

    def reset(self, *, seed=None, options=None):
        seed = None if seed is None else _args.seed(seed)
        super().reset(seed=seed)
        if seed is None and not self._started:
            seed = int(self.np_random.integers(2**63))
        obs = self._worlds.reset_one(0, seed)
        self._started = True
        self._cells = [self.uav]
        self._actions = []
        return obs, self._task_info()

    def _task_info(self):
        return task_info(self._worlds, 0)

    def step(self, action):
        a = action_index(action, self.action_space.n)
        if not self._started:
            raise ResetNeeded("step() before reset(): call reset() first")
        return self._step(a)

    def _step(self, a):
        try:
            obs, reward, truncated, aoi, power_mw, outage, device, cell = (
                self._worlds.step_one(0, a)
            )
        except RuntimeError as e:
            raise ResetNeeded(str(e)) from None
        self._cells.append(cell)
        self._actions.append(a)
        info = {"aoi": aoi, "power_mw": power_mw, "outage": outage, "device": device}
        info.update(self._task_info())
        return obs, reward, False, truncated, info

    def render(self):
        """An RGB array (H, W, 3) of the grid, the rain zone, the devices (coloured by AoI) and
        the UAV with its path so far."""
        return _render.frame(self._worlds, 0, trajectory=self._cells)

    def render_trajectory(self, cells=None):
        """An RGB array of a whole path (default: this episode's) over the world."""
        return _render.frame(self._worlds, 0, trajectory=self._cells if cells is None else cells)

    # What the world is, for drawing, policies and users.
    @property
    def uav(self):
        """The UAV's cell (x, y)."""
        return self._worlds.state(0)[0]

    @property
    def t(self):
        """The step of the episode the env stands at: 0 after reset, the horizon at its end."""
        return len(self._cells) - 1

    @property
    def rain_zone(self):
        """The rain zone now (x0, y0, x1, y1), or None."""
        return self._worlds.state(0)[2]

    @property
    def trajectory(self):
        """The UAV's cells in this episode so far, from the start cell."""
        return list(self._cells)
