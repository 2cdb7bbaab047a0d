"""Python arguments to what the native ``Worlds`` takes: world keys as ``--set`` overrides in
TOML syntax, and checks of the arguments Rust would otherwise reject with a less helpful error.
Every error is a ``ValueError`` naming the argument and its value."""

import json
import math
import operator

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
    raise ValueError(
        f"{key} = {value!r}: expected a number, a bool, a string or a list of them"
    )


def overrides(world, extra):
    """``world.KEY=VALUE`` for every world key given as a keyword, then the raw ``extra``
    overrides (``section.key=value``, as the CLI's ``--set``)."""
    out = [f"world.{k}={toml_value('world.' + k, v)}" for k, v in world.items()]
    for o in extra or ():
        if not isinstance(o, str) or "=" not in o:
            raise ValueError(f"set = {o!r}: expected 'KEY=VALUE', e.g. 'world.devices=5'")
        out.append(o)
    return out


def natural(key, value, upper=None):
    """``value`` as a non-negative integer (below ``upper`` if given)."""
    try:
        n = operator.index(value)
    except TypeError:
        raise ValueError(f"{key} = {value!r}: expected an integer") from None
    if n < 0 or (upper is not None and n >= upper):
        bound = f" below {upper}" if upper is not None else ""
        raise ValueError(f"{key} = {value!r}: expected an integer >= 0{bound}")
    return n


def seed(value, key="seed"):
    return natural(key, value, upper=2**64)


def lam(value):
    if value is None:
        return None
    try:
        return float(value)
    except (TypeError, ValueError):
        raise ValueError(f"lam = {value!r}: expected a finite number >= 0") from None


def rain(value):
    """A rain zone as (x0, y0, x1, y1): a sequence of four cells or a dict with those keys."""
    if value is None:
        return None
    if isinstance(value, dict):
        try:
            value = [value[k] for k in ("x0", "y0", "x1", "y1")]
        except KeyError:
            raise ValueError(f"rain = {value!r}: expected the keys x0, y0, x1, y1") from None
    if isinstance(value, str) or len(value) != 4:
        raise ValueError(f"rain = {value!r}: expected four cell indices (x0, y0, x1, y1)")
    try:
        return tuple(natural("rain", v, upper=2**32) for v in value)
    except ValueError:
        raise ValueError(
            f"rain = {value!r}: expected four cell indices (x0, y0, x1, y1), each >= 0"
        ) from None


def native_kwargs(config, task, lam_, rain_, rain_moves_every, normalised, set_, world):
    """The keyword arguments of ``_uavmeta.Worlds`` (after ``num_envs``)."""
    return dict(
        normalised=bool(normalised),
        config=None if config is None else str(config),
        task=task,
        lam=lam(lam_),
        rain=rain(rain_),
        rain_moves_every=None
        if rain_moves_every is None
        else natural("rain_moves_every", rain_moves_every, upper=2**32),
        overrides=overrides(world, set_),
    )
