"""Python arguments to what the native ``Worlds`` takes: world keys as ``--set`` overrides in
TOML syntax, and checks of the arguments Rust would otherwise reject with a less helpful error.
Every error names the argument, its value and what was expected: a ``TypeError`` for a value of
the wrong type, a ``ValueError`` for one out of range."""

import json
import math
import operator
import os

import numpy as np


def toml_value(key, value):
    """``value`` written as a TOML value, for the override ``KEY=VALUE``."""
    if isinstance(value, (bool, np.bool_)):
        return "true" if value else "false"
    if isinstance(value, (int, np.integer)):
        return str(int(value))
    if isinstance(value, (float, np.floating)):
        value = float(value)
        if math.isnan(value):
            return "nan"
        if math.isinf(value):
            return "inf" if value > 0 else "-inf"
        return repr(value)
    if isinstance(value, str):
        return json.dumps(value)
    if isinstance(value, (list, tuple, np.ndarray)):
        return "[" + ", ".join(toml_value(key, v) for v in value) + "]"
    raise TypeError(
        f"{key} = {value!r}: expected a number, a bool, a string or a list of them"
    )


def overrides(world, extra):
    """``world.KEY=VALUE`` for every world key given as a keyword, then the raw ``extra``
    overrides (``section.key=value``, as the CLI's ``--set``)."""
    out = [f"world.{k}={toml_value('world.' + k, v)}" for k, v in world.items()]
    if extra is None:
        return out
    if isinstance(extra, (str, bytes)) or not isinstance(extra, (list, tuple)):
        raise TypeError(
            f"set = {extra!r}: expected a list of 'KEY=VALUE' strings, e.g. ['world.devices=5']"
        )
    for i, o in enumerate(extra):
        if not isinstance(o, str):
            raise TypeError(f"set[{i}] = {o!r}: expected a 'KEY=VALUE' string, e.g. 'world.devices=5'")
        if "=" not in o:
            raise ValueError(f"set[{i}] = {o!r}: expected 'KEY=VALUE', e.g. 'world.devices=5'")
        out.append(o)
    return out


def natural(key, value, upper=None):
    """``value`` as a non-negative integer (below ``upper`` if given)."""
    if isinstance(value, (bool, np.bool_)):
        raise TypeError(f"{key} = {value!r}: expected an integer, not a bool")
    try:
        n = operator.index(value)
    except TypeError:
        raise TypeError(f"{key} = {value!r}: expected an integer") from None
    if n < 0 or (upper is not None and n >= upper):
        bound = f" below {upper}" if upper is not None else ""
        raise ValueError(f"{key} = {value!r}: expected an integer >= 0{bound}")
    return n


def seed(value, key="seed"):
    return natural(key, value, upper=2**64)


def lam(value, key="lam"):
    if value is None:
        return None
    if isinstance(value, (str, bytes, bool, np.bool_)) or not isinstance(
        value, (int, float, np.integer, np.floating)
    ):
        raise TypeError(f"{key} = {value!r}: expected a finite number >= 0")
    try:
        return float(value)
    except OverflowError:
        raise ValueError(f"{key} = {value!r}: expected a finite number >= 0") from None


def rain(value, key="rain"):
    """A rain zone as (x0, y0, x1, y1): a sequence of four cells or a dict with those keys."""
    if value is None:
        return None
    if isinstance(value, dict):
        try:
            value = [value[k] for k in ("x0", "y0", "x1", "y1")]
        except KeyError:
            raise ValueError(f"{key} = {value!r}: expected the keys x0, y0, x1, y1") from None
    if isinstance(value, (str, bytes)) or not hasattr(value, "__len__"):
        raise TypeError(f"{key} = {value!r}: expected four cell indices (x0, y0, x1, y1)")
    if len(value) != 4:
        raise ValueError(f"{key} = {value!r}: expected four cell indices (x0, y0, x1, y1)")
    try:
        return tuple(natural(key, v, upper=2**32) for v in value)
    except ValueError:
        raise ValueError(
            f"{key} = {value!r}: expected four cell indices (x0, y0, x1, y1), each >= 0"
        ) from None
    except TypeError:
        raise TypeError(
            f"{key} = {value!r}: expected four integer cell indices (x0, y0, x1, y1)"
        ) from None


def moves_every(value, key="rain_moves_every"):
    return None if value is None else natural(key, value, upper=2**32)


def path(value, key):
    """A file argument as a str (``os.PathLike`` or ``str``), or a TypeError naming it."""
    if value is None:
        return None
    if isinstance(value, os.PathLike):
        value = os.fspath(value)
    if not isinstance(value, str):
        raise TypeError(f"{key} = {value!r}: expected a path (str or os.PathLike)")
    return value


def layout(value, key="layout"):
    """A device layout: None (the config's), a ``world.layout_seed``, or one (x, y) cell per
    device."""
    if value is None or isinstance(value, (int, np.integer)) and not isinstance(value, bool):
        return None if value is None else seed(value, key)
    if isinstance(value, (str, bytes, bool)) or not hasattr(value, "__len__"):
        raise TypeError(
            f"{key} = {value!r}: expected a layout seed or a list of (x, y) device cells"
        )
    cells = []
    for j, cell in enumerate(value):
        if isinstance(cell, (str, bytes)) or not hasattr(cell, "__len__") or len(cell) != 2:
            raise TypeError(f"{key}[{j}] = {cell!r}: expected an (x, y) cell")
        cells.append(tuple(natural(f"{key}[{j}]", c, upper=2**32) for c in cell))
    return cells


# What ``task_of`` reports beside a task's parameters, so that its dict is a task entry too.
_REPORTED = {"task_id", "name", "layout_id"}


def task_entry(entry, i):
    """Entry ``i`` of a task list as (task name, lam, rain, rain_moves_every, layout): a task
    name of the config, a lambda, or a dict of ``lam``, ``rain``, ``rain_moves_every`` (or
    ``task``) and ``layout`` (or ``device_cells``), such as ``env.task_of(i)`` returns."""
    key = f"tasks[{i}]"
    if isinstance(entry, str):
        return (entry, None, None, None, None)
    if isinstance(entry, (int, float, np.integer, np.floating)) and not isinstance(entry, bool):
        return (None, lam(entry, key), None, None, None)
    if isinstance(entry, dict):
        known = {"task", "lam", "rain", "rain_moves_every", "layout", "device_cells"}
        unknown = set(entry) - known - _REPORTED
        if unknown:
            raise ValueError(
                f"{key} has {sorted(unknown)}: expected the keys task, lam, rain, "
                "rain_moves_every, layout"
            )
        if "layout" in entry and "device_cells" in entry:
            raise ValueError(
                f"{key} has layout and device_cells: expected one of them (device_cells is "
                "a layout)"
            )
        name = entry.get("task")
        if name is not None and not isinstance(name, str):
            raise TypeError(f"{key}['task'] = {name!r}: expected a task name")
        return (
            name,
            lam(entry.get("lam"), f"{key}['lam']"),
            rain(entry.get("rain"), f"{key}['rain']"),
            moves_every(entry.get("rain_moves_every"), f"{key}['rain_moves_every']"),
            layout(entry.get("layout", entry.get("device_cells")), f"{key}['layout']"),
        )
    raise TypeError(
        f"{key} = {entry!r}: expected a task name, a lambda or a dict of lam, rain, "
        "rain_moves_every, layout"
    )


def native_kwargs(config, task, lam_, rain_, rain_moves_every, normalised, set_, world, tasks=None):
    """The keyword arguments of ``_uavmeta.Worlds`` (after ``num_envs``)."""
    if task is not None and not isinstance(task, str):
        raise TypeError(f"task = {task!r}: expected the name of a task of the config")
    if not isinstance(normalised, (bool, np.bool_)):
        raise TypeError(f"normalised = {normalised!r}: expected True or False")
    kwargs = dict(
        normalised=bool(normalised),
        config=path(config, "config"),
        task=task,
        lam=lam(lam_),
        rain=rain(rain_),
        rain_moves_every=moves_every(rain_moves_every),
        overrides=overrides(world, set_),
    )
    kwargs.update(task_source(tasks))
    return kwargs


def task_source(tasks):
    """``tasks`` (None, a list of tasks, or a ``TaskSampler``) as the native ``tasks``,
    ``draw`` and ``ranges`` arguments."""
    from .tasks import TaskSampler

    if tasks is None:
        return {}
    if isinstance(tasks, TaskSampler):
        return tasks._native()
    if isinstance(tasks, (list, tuple)):
        return dict(tasks=[task_entry(t, i) for i, t in enumerate(tasks)], draw=False)
    raise TypeError(
        f"tasks = {tasks!r}: expected a list of tasks (names, lambdas or dicts of lam, rain, "
        "rain_moves_every) or a uavmeta.TaskSampler"
    )
