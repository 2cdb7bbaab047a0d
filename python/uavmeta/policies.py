"""The heuristic behaviour policies as batched functions of observations.

Each is built for an env (a ``UavEnv``, a ``VectorEnv`` or a ``gymnasium.make`` of them), whose
task it knows (device cells, deltas, powers, the configured rain zone; on an env of several
tasks, the one its first sub-env runs when the policy is built, layout included: to act on
another task, build one on ``uavmeta.VectorEnv(1, tasks=[env.task_of(i)])``), and maps
observations as that env returns them (raw or normalised), one (2 + K,) row or an (N, 2 + K)
batch, to action indices. They are the Rust policies of ``uavmeta env rollout --policy NAME``, so both choose the
same actions:

- ``random(env, seed)``: uniform over the 5K actions, one draw per row from a stream seeded by
  ``seed`` (the CLI's ``--seed``);
- ``stalest(env)``: serve the device with the largest delta_k A_k, fly towards it;
- ``greedy(env)``: serve the device that makes this step cheapest, fly towards the stalest;
- ``planner(env)``: the planner reference (docs/MODEL.md section 5), a search that knows the world, the
  measure of what is achievable. Call it with the step ``t`` the observations are at
  (``policy(obs, t=env.t)``): it plans the remaining T - t steps from each row, exactly where the
  rain does not move (with the task's configured zone where it does). It keeps its plan while
  the observations follow it, so an episode stepped one observation at a time plans once.

A policy learned by the command line is one more: ``checkpoint(env, path, epsilon, seed)`` is the
greedy policy of a saved Q-network (``uavmeta env rollout --policy q:EPSILON:PATH``), run in numpy
from the checkpoint's safetensors weights, so no libtorch is needed.
"""

import json
import pathlib
import warnings
import zlib

import numpy as np

from ._uavmeta import Heuristic as _Heuristic
from ._uavmeta import checkpoint_spec as _checkpoint_spec

NAMES = ("random", "stalest", "greedy", "planner")


class HeuristicPolicy:
    """``policy(obs)``: an action index for one observation, an int64 array for a batch."""

    def __init__(self, name, env, seed=0):
        worlds = _worlds_of(env)
        self.name = name
        self._native = _Heuristic(name, worlds, normalised=worlds.normalised, seed=seed)
        self._horizon = worlds.horizon

    def __call__(self, obs, t=0):
        if isinstance(t, (bool, np.bool_)) or not isinstance(t, (int, np.integer)):
            raise TypeError(f"t = {t!r}: expected the integer step of the episode, 0..{self._horizon}")
        if not 0 <= t < self._horizon:
            raise ValueError(f"t = {t!r}: expected a step of the episode, 0..{self._horizon}")
        try:
            obs = np.asarray(obs, dtype=np.float32)
        except (TypeError, ValueError):
            raise TypeError(
                f"observations = {obs!r}: expected an array of (2 + K,) or (N, 2 + K) numbers"
            ) from None
        if obs.ndim not in (1, 2):
            raise ValueError(
                f"observations of shape {obs.shape}: expected (2 + K,) or (N, 2 + K)"
            )
        actions = self._native(np.ascontiguousarray(np.atleast_2d(obs)), t=int(t))
        return int(actions[0]) if obs.ndim == 1 else actions

    def __repr__(self):
        return f"HeuristicPolicy({self.name!r})"


def random(env, seed=0):
    return HeuristicPolicy("random", env, seed)


def stalest(env):
    return HeuristicPolicy("stalest", env)


def greedy(env):
    return HeuristicPolicy("greedy", env)


def planner(env):
    return HeuristicPolicy("planner", env)


def make(name, env, seed=0):
    """The policy called ``name`` for ``env``: one of :data:`NAMES`, or ``q:EPSILON:PATH`` as the
    command line's ``--policy`` writes a saved Q-network's (:func:`checkpoint`)."""
    if isinstance(name, str) and name.startswith("q:"):
        try:
            epsilon, path = _checkpoint_spec(name)
        except ValueError as e:
            raise ValueError(f"{e} (the command line's q:EPSILON:PATH)") from None
        return checkpoint(env, path, epsilon, seed)
    if name not in NAMES:
        raise ValueError(
            f"policy = {name!r}: expected one of {', '.join(NAMES)} or q:EPSILON:PATH"
        )
    return HeuristicPolicy(name, env, seed)


def _worlds_of(env):
    for e in (env, getattr(env, "unwrapped", None)):
        worlds = getattr(e, "_worlds", None)
        if worlds is not None:
            return worlds
    raise ValueError(f"env = {env!r}: expected a uavmeta UavEnv or VectorEnv")


class QNetworkPolicy:
    """``policy(obs)``: the greedy action of a Q-network that ``uavmeta`` saved (``train``,
    ``meta-train``, ``meta-test``, ``collect``'s online agent), ``argmax_a Q(s, a)`` on the
    normalised observation as the command line computes it; with probability ``epsilon`` a
    uniform random action instead, from a numpy stream seeded by ``seed`` (not the command
    line's stream: with ``epsilon > 0`` the two choose alike in distribution only).

    The network is the model's MLP (docs/MODEL.md section 5) (ReLU between layers) with the widths its metadata records.
    ``q_values(obs)`` gives the Q-values themselves. Q-values are float32 sums taken in another
    order than libtorch's, so an action whose two best Q-values differ in the last bits may
    differ from the command line's."""

    def __init__(self, env, path, epsilon=0.0, seed=0):
        worlds = _worlds_of(env)
        if not (isinstance(epsilon, (int, float)) and 0.0 <= epsilon <= 1.0):
            raise ValueError(f"epsilon = {epsilon!r}: expected a probability in [0, 1]")
        self.path = pathlib.Path(path)
        self.epsilon = float(epsilon)
        self.meta = _checkpoint_meta(self.path)
        obs_len, actions = 2 + worlds.devices, 5 * worlds.devices
        for key, found, expected in (
            ("obs_len", self.meta.get("obs_len"), obs_len),
            ("actions", self.meta.get("actions"), actions),
        ):
            if found != expected:
                raise ValueError(
                    f"checkpoint {self.path}: {key} = {found!r}, but the env's world "
                    f"(world.devices = {worlds.devices}) has {expected}"
                )
        if self.meta.get("world_hash") != worlds.world_hash:
            warnings.warn(
                f"checkpoint {self.path} was trained in another world (hash "
                f"{self.meta.get('world_hash')!r}) than the env's ({worlds.world_hash}); the "
                "sizes match, so it loads",
                stacklevel=3,
            )
        self._layers = _checkpoint_layers(self.path, self.meta)
        self._acting = acting_rule(self.meta, _checkpoint_config(self.path))
        self._scale = None if worlds.normalised else np.asarray(worlds.observation_scale, np.float32)
        self._actions = actions
        self._rng = np.random.default_rng(seed)

    def q_values(self, obs):
        """Q(s, .) of one (2 + K,) observation or an (N, 2 + K) batch, as float32."""
        return self.outputs(obs)[..., : self._actions]

    def outputs(self, obs):
        """The network's outputs: Q(s, .), then for a BCQ network its imitation logits."""
        x = np.atleast_2d(np.asarray(obs, dtype=np.float32))
        if x.ndim != 2 or x.shape[1] != self._layers[0][0].shape[1]:
            raise ValueError(
                f"observations of shape {np.shape(obs)}: expected (2 + K,) or (N, 2 + K) "
                f"with 2 + K = {self._layers[0][0].shape[1]}"
            )
        if self._scale is not None:
            x = x / self._scale
        for i, (weight, bias) in enumerate(self._layers):
            x = x @ weight.T + bias
            if i + 1 < len(self._layers):
                x = np.maximum(x, 0.0)
        return x[0] if np.ndim(obs) == 1 else x

    def __call__(self, obs, t=0):
        values = self._acting(np.atleast_2d(self.outputs(obs)))
        actions = values.argmax(axis=1).astype(np.int64)
        if self.epsilon > 0.0:
            explore = self._rng.random(len(actions)) < self.epsilon
            actions[explore] = self._rng.integers(0, self._actions, explore.sum())
        return int(actions[0]) if np.ndim(obs) == 1 else actions

    def __repr__(self):
        return f"QNetworkPolicy({str(self.path)!r}, epsilon={self.epsilon})"


def checkpoint(env, path, epsilon=0.0, seed=0):
    """The greedy policy of the Q-network saved at ``path`` (the checkpoint's name without its
    extension: ``runs/default/seed-0/inits/w0`` for ``w0.json`` and ``w0.safetensors``), epsilon-
    greedy with ``epsilon > 0``: ``uavmeta env rollout --policy q:EPSILON:PATH`` in numpy."""
    return QNetworkPolicy(env, path, epsilon, seed)


def acting_rule(meta, config_toml):
    """The function from a checkpoint's network outputs [N, heads * A] to the values whose argmax
    is its action, as the command line acts (learner/src/algorithm.rs): the Q-values, or for a
    discrete BCQ network (two heads) the Q-values of the actions its imitation head supports
    (learner/src/bcq.rs), with the ``[learner] bcq_threshold`` of the config saved beside it."""
    heads, algorithm = int(meta.get("heads", 1)), str(meta.get("algorithm", ""))
    if heads == 1:
        return lambda out: out
    if heads == 2 and algorithm.split("-")[0] == "bcq":
        return lambda out: bcq_supported_values(out, _bcq_threshold(config_toml))
    raise ValueError(
        f"checkpoint of {algorithm!r} with {heads} heads: this uavmeta acts only on one head, or "
        "on discrete BCQ's two"
    )


def bcq_supported_values(outputs, threshold):
    """learner/src/bcq.rs's ``supported_values``: Q-values shifted positive where the imitation
    probability is at least ``threshold`` times the most likely action's, 0 elsewhere."""
    outputs = np.asarray(outputs, np.float32)
    a = outputs.shape[-1] // 2
    q, logits = outputs[..., :a], outputs[..., a:]
    log_ratio = logits - logits.max(axis=-1, keepdims=True)
    with np.errstate(divide="ignore"):
        supported = log_ratio >= np.log(np.float32(threshold))
    return (q - q.min(axis=-1, keepdims=True) + np.float32(1e-5)) * supported


def _bcq_threshold(config_toml, default=0.3):
    """``[learner] bcq_threshold`` of a saved config (every saved config writes it)."""
    import re

    section = re.search(r"^\[learner\]\n(.*?)(?=^\[|\Z)", config_toml or "", re.M | re.S)
    found = section and re.search(r"^bcq_threshold\s*=\s*([0-9.eE+-]+)", section.group(1), re.M)
    return float(found.group(1)) if found else default


def _checkpoint_config(path):
    config = path.with_name(path.name + ".toml")
    return config.read_text() if config.exists() else None


def _checkpoint_meta(path):
    meta_path = path.with_name(path.name + ".json")
    try:
        meta = json.loads(meta_path.read_text())
    except OSError as e:
        raise ValueError(f"checkpoint {path}: cannot read {meta_path}: {e.strerror}") from None
    except json.JSONDecodeError as e:
        raise ValueError(f"checkpoint {path}: {meta_path} is not checkpoint metadata: {e}") from None
    if not isinstance(meta, dict) or meta.get("format_version") != 1:
        raise ValueError(
            f"checkpoint {path}: {meta_path} has format_version "
            f"{meta.get('format_version') if isinstance(meta, dict) else None!r}, expected 1"
        )
    return meta


def _checkpoint_layers(path, meta):
    """[(weight [out, in], bias [out])] of layer0, layer1, ... after checking the file's length
    and CRC32 against the metadata, as the command line does."""
    from safetensors.numpy import load as load_safetensors

    weights_path = path.with_name(path.name + ".safetensors")
    try:
        data = weights_path.read_bytes()
    except OSError as e:
        raise ValueError(f"checkpoint {path}: cannot read {weights_path}: {e.strerror}") from None
    expected_len, expected_crc = meta.get("weights_len"), meta.get("weights_crc32")
    if not (isinstance(expected_len, int) and isinstance(expected_crc, int)):
        raise ValueError(f"checkpoint {path}: its metadata records no weights_len and weights_crc32")
    if len(data) != expected_len or zlib.crc32(data) != expected_crc:
        raise ValueError(
            f"checkpoint {path}: {weights_path} is {len(data)} bytes with CRC32 "
            f"{zlib.crc32(data):#010x}, its metadata records {expected_len} bytes with CRC32 "
            f"{expected_crc:#010x}"
        )
    tensors = load_safetensors(data)
    widths = [meta["obs_len"], *meta.get("hidden", []), meta["actions"] * int(meta.get("heads", 1))]
    layers = []
    for i, (n_in, n_out) in enumerate(zip(widths, widths[1:])):
        weight, bias = tensors.get(f"layer{i}.weight"), tensors.get(f"layer{i}.bias")
        if weight is None or bias is None or weight.shape != (n_out, n_in) or bias.shape != (n_out,):
            raise ValueError(
                f"checkpoint {path}: {weights_path} lacks layer{i} of shape ({n_out}, {n_in}) "
                f"that its metadata's widths {widths} call for"
            )
        layers.append((weight.astype(np.float32), bias.astype(np.float32)))
    return layers
