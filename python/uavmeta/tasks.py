"""``TaskSampler``: a task distribution that a ``VectorEnv`` (or a ``UavEnv``) draws a new task
from at every reset, as meta-RL training asks. The draws run in Rust inside the batched step, so
a resampling env steps as fast as a fixed one."""

import numbers

from . import _args


class TaskSampler:
    """A new task at every reset of every sub-env.

    - ``TaskSampler(tasks)``: one of ``tasks`` uniformly (names of the config's tasks, lambdas,
      or dicts of ``lam``, ``rain``, ``rain_moves_every``, ``layout``); ``info["task_id"]`` is
      its index.
    - ``TaskSampler(lam=(lo, hi), rain_probability=p, rain_size=(a, b),
      rain_moves_every=(None, 10), layouts=(None, 7))``: lambda uniform in [lo, hi]; with
      probability p a rain zone of sides uniform in a..=b cells placed uniformly on the grid,
      moving every one of ``rain_moves_every`` steps (None: it stays); the device layout one of
      ``layouts`` (None: the config's; a ``world.layout_seed``; or one (x, y) cell per device);
      ``info["task_id"]`` identifies the draw, ``info["layout_id"]`` the layout's index where
      there are several.

    A draw depends only on the world seed of the episode it starts, so ``reset(seed=S)``
    reproduces every env's sequence of tasks, and a ``VectorEnv`` equals a ``SyncVectorEnv``
    of ``UavEnv``\\ s with the same sampler.
    """

    def __init__(self, tasks=None, *, lam=None, rain_probability=0.0, rain_size=(1, 3),
                 rain_moves_every=(None,), layouts=(None,)):
        if (tasks is None) == (lam is None):
            raise ValueError(
                "TaskSampler: expected either a list of tasks or lam=(lo, hi) ranges, "
                f"got tasks = {tasks!r} and lam = {lam!r}"
            )
        self.tasks = None
        self.ranges = None
        if tasks is not None:
            if not isinstance(tasks, (list, tuple)):
                raise TypeError(f"tasks = {tasks!r}: expected a list of tasks")
            self.tasks = [_args.task_entry(t, i) for i, t in enumerate(tasks)]
            self._list = list(tasks)
            return
        self.ranges = (
            _pair(lam, "lam", float),
            _probability(rain_probability),
            _pair(rain_size, "rain_size", lambda v: _args.natural("rain_size", v, upper=2**32)),
            _choices(rain_moves_every),
            _layouts(layouts),
        )

    def _native(self):
        if self.tasks is not None:
            return dict(tasks=self.tasks, draw=True)
        return dict(ranges=self.ranges)

    def __repr__(self):
        if self.tasks is not None:
            return f"TaskSampler({self._list!r})"
        lam, p, size, moves, layouts = self.ranges
        return (
            f"TaskSampler(lam={lam}, rain_probability={p}, rain_size={size}, "
            f"rain_moves_every={moves}, layouts={layouts})"
        )


def _pair(value, key, convert):
    if isinstance(value, (str, bytes)) or not hasattr(value, "__len__"):
        raise TypeError(f"{key} = {value!r}: expected a pair (lo, hi)")
    if len(value) != 2:
        raise ValueError(f"{key} = {value!r}: expected a pair (lo, hi)")
    for v in value:
        if isinstance(v, bool) or not isinstance(v, numbers.Real):
            raise TypeError(f"{key} = {value!r}: expected a pair of numbers (lo, hi)")
    return tuple(convert(v) for v in value)


def _probability(p):
    if isinstance(p, bool) or not isinstance(p, numbers.Real):
        raise TypeError(f"rain_probability = {p!r}: expected a probability in [0, 1]")
    return float(p)


def _choices(moves):
    if moves is None or isinstance(moves, numbers.Integral):
        moves = (moves,)
    if isinstance(moves, (str, bytes)) or not hasattr(moves, "__iter__"):
        raise TypeError(
            f"rain_moves_every = {moves!r}: expected a list of step counts (None: the rain stays)"
        )
    return [_args.moves_every(m, f"rain_moves_every[{i}]") for i, m in enumerate(moves)]


def _layouts(layouts):
    if isinstance(layouts, (str, bytes)) or not isinstance(layouts, (list, tuple)):
        raise TypeError(
            f"layouts = {layouts!r}: expected a list of layouts (None: the config's; a layout "
            "seed; or a list of (x, y) device cells)"
        )
    return [_args.layout(v, f"layouts[{i}]") for i, v in enumerate(layouts)]
