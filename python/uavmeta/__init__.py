"""The uavmeta UAV world from Python.

The world of the paper "Resilient UAV Trajectory Planning via Few-Shot Meta-Offline
Reinforcement Learning" (docs/MODEL.md sections 1-3 of this repository), stepped by the same Rust code
as the ``uavmeta`` command line, without libtorch:

- :class:`UavEnv`, a ``gymnasium.Env``, registered as ``uavmeta/UAV-v0``;
- :class:`VectorEnv`, N worlds stepped in one call in Rust (Gymnasium's ``VectorEnv`` API,
  next-step autoreset), each of its own task (``tasks=[...]``) or drawing a new one at every
  reset (``tasks=TaskSampler(...)``), also reachable as ``gymnasium.make_vec("uavmeta/UAV-v0",
  n, vectorization_mode="vector_entry_point")``;
- :class:`TeamVectorEnv`, N worlds of a UAV team (``uavs=2``, docs/MODEL.md section 11)
  stepped in one call, and :mod:`uavmeta.pettingzoo`, one team's world as a PettingZoo
  ``ParallelEnv`` (``pip install uavmeta[pettingzoo]``);
- :func:`evaluate`, :func:`references` and :func:`normalised_score`: a policy scored as the
  tables and the command line score it, to the digit;
- :mod:`uavmeta.policies`, the heuristics (random, stalest, greedy), the planner and any saved
  Q-network (``checkpoint``) as batched functions of observations;
- :func:`load_dataset`, a ``.uavds`` file as numpy arrays with its task's metadata;
- :mod:`uavmeta.render`, RGB pictures of the world and of a trajectory.

Actions are ``a = move * K + device`` with the moves in :data:`MOVES` order (``move * (K + 1) +
target`` with ``idle_action=True``, target K serving no device).
"""

import gymnasium

from ._uavmeta import ACTION_MOVES as _MOVES
from ._uavmeta import DatasetError, episode_seed
from .dataset import Dataset, load_dataset
from .env import ResetNeeded, UavEnv
from .evaluate import REFERENCES, Estimate, Score, evaluate, normalised_score, references
from .tasks import TaskSampler
from .team import TeamVectorEnv
from .vector import VectorEnv
from . import policies, render

#: The five moves in action-index order: north (0, +1), south (0, -1), east (+1, 0),
#: west (-1, 0), hover.
MOVES = tuple(_MOVES)

ENV_ID = "uavmeta/UAV-v0"


def action(move, device, devices=10):
    """The action index of flying ``move`` (a name of :data:`MOVES`) and serving ``device``
    among ``devices`` (K): ``MOVES.index(move) * K + device``."""
    if move not in MOVES:
        raise ValueError(f"move = {move!r}: expected one of {', '.join(MOVES)}")
    if not 0 <= device < devices:
        raise ValueError(f"device = {device!r}: expected 0 <= device < {devices}")
    return MOVES.index(move) * devices + device


def action_parts(a, devices=10):
    """(move name, device) of action index ``a`` among K = ``devices`` devices."""
    if not 0 <= a < len(MOVES) * devices:
        raise ValueError(f"action = {a!r}: expected 0 <= action < {len(MOVES) * devices}")
    return MOVES[a // devices], a % devices

if ENV_ID not in gymnasium.registry:
    gymnasium.register(
        id=ENV_ID,
        entry_point="uavmeta.env:UavEnv",
        vector_entry_point="uavmeta.vector:VectorEnv",
    )

__all__ = [
    "ENV_ID",
    "MOVES",
    "REFERENCES",
    "Dataset",
    "DatasetError",
    "Estimate",
    "ResetNeeded",
    "Score",
    "TaskSampler",
    "TeamVectorEnv",
    "UavEnv",
    "VectorEnv",
    "action",
    "action_parts",
    "episode_seed",
    "evaluate",
    "load_dataset",
    "normalised_score",
    "policies",
    "references",
    "render",
]
