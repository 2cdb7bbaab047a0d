"""A Q-network that ``uavmeta`` saved as a ``torch.nn.Module``, and back: load ``w0`` (or any
checkpoint), fine-tune it in PyTorch, save it where ``uavmeta eval`` and ``--policy q:0:PATH``
read it. Pure Python, torch and safetensors; no libtorch of ours.

A checkpoint ``P`` is three files (learner/src/checkpoint.rs): ``P.safetensors``
(``layer{i}.weight`` [out, in] and ``layer{i}.bias`` [out], float32), ``P.json`` (format 1:
algorithm, obs_len, actions, hidden, heads where not 1, world_hash, epoch and the weights file's
length and CRC32) and ``P.toml``, the config of the run that wrote it.

    net = uavmeta.nn.load_q_network("runs/default/seed-0/inits/w0")
    q = net(torch.from_numpy(obs))        # obs normalised: UavEnv(normalised=True)
    uavmeta.nn.save_q_network(net, "tuned", like="runs/default/seed-0/inits/w0")
"""

import json
import os
import pathlib
import zlib

import torch
from torch import nn

from .policies import _checkpoint_layers, _checkpoint_meta, acting_rule

FORMAT_VERSION = 1


class QNetwork(nn.Module):
    """The model's MLP (docs/MODEL.md section 5): ``layer0`` .. ``layer{n}`` linear layers with ReLU between them, from the
    normalised observation (2 + K values) to the 5K Q-values (times ``heads``: a discrete BCQ
    network's imitation logits follow its Q-values).

    ``meta`` is the checkpoint metadata it was loaded with (or built from), ``config_toml`` the
    config beside it (or None)."""

    def __init__(self, obs_len, actions, hidden=(256, 256), heads=1):
        super().__init__()
        obs_len, actions, hidden = int(obs_len), int(actions), [int(h) for h in hidden]
        widths = [obs_len, *hidden, actions * int(heads)]
        self.depth = len(widths) - 1
        for i, (n_in, n_out) in enumerate(zip(widths, widths[1:])):
            self.add_module(f"layer{i}", nn.Linear(n_in, n_out))
        self.meta = dict(format_version=FORMAT_VERSION, algorithm="python", obs_len=obs_len,
                         actions=actions, hidden=hidden, world_hash=None, epoch=0)
        if int(heads) != 1:
            self.meta["heads"] = int(heads)
        self.config_toml = None

    def forward(self, obs):
        x = obs  # [B, 2 + K], normalised
        for i in range(self.depth):
            x = getattr(self, f"layer{i}")(x)  # [B, width_i]
            if i + 1 < self.depth:
                x = torch.relu(x)
        return x  # [B, 5K]

    def act(self, obs):
        """The greedy action of each row of a numpy batch, as the command line acts with the
        algorithm that trained it: ``uavmeta.evaluate`` takes it."""
        with torch.no_grad():
            out = self(torch.as_tensor(obs, dtype=torch.float32)).numpy()
        return acting_rule(self.meta, self.config_toml)(out).argmax(axis=-1)


def _path(path, key="path"):
    if not isinstance(path, (str, os.PathLike)):
        raise TypeError(f"{key} = {path!r}: expected a checkpoint path (str or os.PathLike)")
    return pathlib.Path(path)


def load_q_network(path):
    """The network saved at ``path`` (without extension), after the checks the command line
    makes (format, the widths against the weights, the weights' length and CRC32); a damaged
    or missing checkpoint raises ``ValueError`` naming the file."""
    path = _path(path)
    meta = _checkpoint_meta(path)
    layers = _checkpoint_layers(path, meta)
    net = QNetwork(meta["obs_len"], meta["actions"], meta.get("hidden", []), meta.get("heads", 1))
    with torch.no_grad():
        for i, (weight, bias) in enumerate(layers):
            layer = getattr(net, f"layer{i}")
            layer.weight.copy_(torch.from_numpy(weight))
            layer.bias.copy_(torch.from_numpy(bias))
    net.meta = dict(meta)
    config = path.with_name(path.name + ".toml")
    net.config_toml = config.read_text() if config.exists() else None
    return net


def save_q_network(net, path, *, like=None, algorithm=None, epoch=None, world_hash=None,
                   config_toml=None):
    """Writes ``net`` (a :class:`QNetwork`) as checkpoint ``path``: the three files the
    command line reads, each written to a temporary name and renamed, the metadata last.

    The world hash and config come from ``like`` (a checkpoint path whose config and hash to
    keep), else from ``net.meta`` / ``net.config_toml`` (what it was loaded with), else from
    the arguments; without a config the command line cannot check the world, so one is
    required."""
    from safetensors.torch import save as save_safetensors

    if not isinstance(net, QNetwork):
        raise TypeError(f"net = {net!r}: expected a uavmeta.nn.QNetwork")
    path = _path(path)
    meta = dict(net.meta)
    config = net.config_toml
    if like is not None:
        like = _path(like, "like")
        meta.update({k: v for k, v in _checkpoint_meta(like).items() if k == "world_hash"})
        config = like.with_name(like.name + ".toml").read_text()
    config = config_toml if config_toml is not None else config
    if world_hash is not None:
        meta["world_hash"] = int(world_hash)
    if config is None or meta.get("world_hash") is None:
        raise ValueError(
            f"save_q_network({str(path)!r}): expected the world it belongs to: like=CHECKPOINT, "
            "or world_hash= and config_toml= (uavmeta.UavEnv(...)._worlds.world_hash and "
            ".config_toml)"
        )
    tensors = {k: v.detach().to("cpu", torch.float32).contiguous() for k, v in net.state_dict().items()}
    weights = save_safetensors(tensors)
    meta.update(
        format_version=FORMAT_VERSION,
        algorithm=algorithm or meta.get("algorithm") or "python",
        epoch=int(epoch if epoch is not None else meta.get("epoch", 0)),
        weights_len=len(weights),
        weights_crc32=zlib.crc32(weights),
    )
    keys = ("format_version", "algorithm", "obs_len", "actions", "hidden", "heads", "world_hash",
            "epoch", "weights_len", "weights_crc32")
    path.parent.mkdir(parents=True, exist_ok=True)
    _write_atomic(path.with_name(path.name + ".safetensors"), weights)
    _write_atomic(path.with_name(path.name + ".toml"), config.encode())
    _write_atomic(path.with_name(path.name + ".json"),
                  json.dumps({k: meta[k] for k in keys if k in meta}).encode())
    return path


def _write_atomic(target, data):
    tmp = target.with_name(f".{target.name}.tmp")
    with open(tmp, "wb") as f:
        f.write(data)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, target)
