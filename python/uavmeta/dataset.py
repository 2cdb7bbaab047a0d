"""``load_dataset``: a ``.uavds`` file (``uavmeta collect``) as numpy arrays."""

from dataclasses import dataclass
from typing import Optional, Tuple

import numpy as np

from . import _args
from ._uavmeta import load_dataset as _load

_ARRAYS = (
    "obs", "action", "reward", "next_obs", "truncated", "terminals", "truncations", "task",
    "actor", "episode", "step", "seq",
)


@dataclass(frozen=True)
class Dataset:
    """One task's transitions, one row each, and what the file and its config say of the task.

    ``obs`` and ``next_obs`` are the raw (n, 2 + K) uint16 observations, or with
    ``normalised=True`` float32 divided by L-1, L-1 and aoi_max exactly as the env's
    ``normalised=True`` gives them; ``action`` int64 indices ``move * K + device``; ``reward``
    float32; ``truncated`` bool (a time limit: bootstrap through it). ``terminals`` (all
    False: the horizon is a time limit, never a terminal state) and ``truncations`` (=
    ``truncated``) are the columns D4RL and Minari name so. ``lam``, ``rain``,
    ``rain_moves_every``, ``role`` and the world's ``grid_cells``, ``horizon``, ``aoi_max``
    and ``observation_scale`` come from the config saved beside the file
    (``FILE.config.toml``), and are None without one.
    """

    obs: np.ndarray
    action: np.ndarray
    reward: np.ndarray
    next_obs: np.ndarray
    truncated: np.ndarray
    terminals: np.ndarray
    truncations: np.ndarray
    task: np.ndarray
    actor: np.ndarray
    episode: np.ndarray
    step: np.ndarray
    seq: np.ndarray
    task_name: str
    task_id: int
    devices: int
    world_hash: int
    chunks: int
    path: str
    normalised: bool = False
    lam: Optional[float] = None
    rain: Optional[Tuple[int, int, int, int]] = None
    rain_moves_every: Optional[int] = None
    role: Optional[str] = None
    config_path: Optional[str] = None
    grid_cells: Optional[int] = None
    horizon: Optional[int] = None
    aoi_max: Optional[int] = None
    observation_scale: Optional[Tuple[float, ...]] = None

    def __len__(self):
        return len(self.reward)

    @property
    def task_params(self):
        """The task's parameters as a dict (``name``, ``task_id``, ``lam``, ``rain``,
        ``rain_moves_every``, ``role``), as ``VectorEnv.task_of`` reports an env's."""
        return dict(
            name=self.task_name, task_id=self.task_id, lam=self.lam, rain=self.rain,
            rain_moves_every=self.rain_moves_every, role=self.role,
        )


def load_dataset(path, config=None, normalised=False):
    """Reads ``path`` whole, checking every chunk's CRC32.

    A damaged file raises ``uavmeta.DatasetError`` (a ``ValueError``) naming the file and the
    byte offset; a missing one ``FileNotFoundError``; a ``path`` or ``config`` that is no
    path ``TypeError``. ``config`` (default ``FILE.config.toml`` if it exists) gives the
    task's lambda and rain and the world's size, after checking the file's world is its world.
    ``normalised=True`` gives the observations as the env's ``normalised=True`` does.
    """
    if path is None:
        raise TypeError("path = None: expected the path of a .uavds file (str or os.PathLike)")
    if not isinstance(normalised, (bool, np.bool_)):
        raise TypeError(f"normalised = {normalised!r}: expected True or False")
    fields = _load(_args.path(path, "path"), _args.path(config, "config"), bool(normalised))
    if fields.get("observation_scale") is not None:
        fields["observation_scale"] = tuple(fields["observation_scale"])
    return Dataset(**fields)
