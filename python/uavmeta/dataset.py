"""``load_dataset``: a ``.uavds`` file (``uavmeta collect``) as numpy arrays."""

from dataclasses import dataclass
from typing import Optional, Tuple

import numpy as np

from ._uavmeta import load_dataset as _load

_ARRAYS = ("obs", "action", "reward", "next_obs", "truncated", "task", "actor", "episode", "step", "seq")


@dataclass(frozen=True)
class Dataset:
    """One task's transitions, one row each, and what the file and its config say of the task.

    ``obs`` and ``next_obs`` are the raw (n, 2 + K) uint16 observations; ``action`` int64
    indices ``move * K + device``; ``reward`` float32; ``truncated`` bool (a time limit:
    bootstrap through it). ``lam``, ``rain``, ``rain_moves_every`` and ``role`` come from the
    config saved beside the file (``FILE.config.toml``), and are None without one.
    """

    obs: np.ndarray
    action: np.ndarray
    reward: np.ndarray
    next_obs: np.ndarray
    truncated: np.ndarray
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
    lam: Optional[float] = None
    rain: Optional[Tuple[int, int, int, int]] = None
    rain_moves_every: Optional[int] = None
    role: Optional[str] = None
    config_path: Optional[str] = None

    def __len__(self):
        return len(self.reward)


def load_dataset(path, config=None):
    """Reads ``path`` whole, checking every chunk's CRC32.

    A damaged file raises ``uavmeta.DatasetError`` (a ``ValueError``) naming the file and the
    byte offset; a missing one ``FileNotFoundError``. ``config`` (default ``FILE.config.toml``
    if it exists) gives the task's lambda and rain, after checking the file's world is its
    world.
    """
    return Dataset(**_load(str(path), None if config is None else str(config)))
