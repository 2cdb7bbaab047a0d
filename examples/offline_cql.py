"""Offline CQL in PyTorch on a dataset `uavmeta collect` wrote, scored as the tables score it.

One file in CleanRL's manner: the arguments, the data, the network, the loss, the loop. Make a
dataset, train, and read the score between random (0) and the planner (100):

    uavmeta collect --config configs/default.toml --task lambda-300 --policy eps:0.3 \\
        --transitions 5000 --seed 1 --out data/lambda-300.uavds
    python examples/offline_cql.py --dataset data/lambda-300.uavds

Conservative Q-learning (Kumar et al. 2020, eq. 4 with the CQL(H) regulariser), discrete actions:

    L(theta) = alpha * E_s[ logsumexp_a Q(s, a) - E_{a~D} Q(s, a) ]
             + 1/2 E_{(s,a,r,s')~D}[ (Q(s, a) - (r + gamma * max_a' Q_target(s', a')))^2 ]

The horizon is a time limit (the dataset's `terminals` are all false), so every target
bootstraps, through the last step of an episode too.
"""

import time
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

import uavmeta
from uavmeta.nn import QNetwork, save_q_network


@dataclass
class Args:
    dataset: str = "data/lambda-300.uavds"
    """a .uavds file of `uavmeta collect`, with its FILE.config.toml beside it"""
    seed: int = 1
    """seed of the network's init and of the minibatches"""
    total_steps: int = 5000
    """gradient steps"""
    batch: int = 256
    """minibatch size"""
    lr: float = 1e-3
    """Adam's learning rate"""
    gamma: float = 0.99
    """discount factor"""
    alpha: float = 1.0
    """weight of the conservative term (CQL's alpha)"""
    reward_scale: float = 0.01
    """rewards times this before the loss sees them (a step costs about 100)"""
    hidden: tuple = (256, 256)
    """hidden layer widths"""
    target_update_every: int = 500
    """gradient steps between hard target-network updates"""
    log_every: int = 500
    """steps between log lines"""
    save: str = ""
    """if set, save the network there as a checkpoint `uavmeta eval --checkpoint` reads"""


def parse_args():
    import argparse

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    for name, default in Args.__dataclass_fields__.items():
        kind = default.type if default.type in (int, float, str) else None
        flag = "--" + name.replace("_", "-")
        if kind is None:
            parser.add_argument(flag, type=int, nargs="+", default=default.default)
        else:
            parser.add_argument(flag, type=kind, default=default.default)
    return Args(**vars(parser.parse_args()))


def main():
    args = parse_args()
    print("| hyperparameter | value |\n| --- | --- |")
    print("\n".join(f"| {k} | {v} |" for k, v in vars(args).items()))
    torch.manual_seed(args.seed)
    rng = np.random.default_rng(args.seed)

    # --- data: normalised as the env's normalised=True, so the network sees what it will act on
    data = uavmeta.load_dataset(args.dataset, normalised=True)
    obs = torch.from_numpy(data.obs)  # [N, 2 + K]
    actions = torch.from_numpy(data.action)  # [N]
    rewards = torch.from_numpy(data.reward.astype(np.float32)) * args.reward_scale  # [N]
    next_obs = torch.from_numpy(data.next_obs)  # [N, 2 + K]
    assert not data.terminals.any()  # a time limit: bootstrap everywhere
    print(f"{args.dataset}: {len(data)} transitions of task {data.task_name} (lambda = {data.lam})")

    # --- network: the model's MLP (docs/MODEL.md section 5), so the result is a checkpoint the command line reads
    env = uavmeta.UavEnv(config=data.config_path, task=data.task_name, normalised=True)
    q = QNetwork(obs.shape[1], env.action_space.n, args.hidden)
    target = QNetwork(obs.shape[1], env.action_space.n, args.hidden)
    target.load_state_dict(q.state_dict())
    optimiser = torch.optim.Adam(q.parameters(), lr=args.lr)

    # --- training loop
    start = time.time()
    for step in range(1, args.total_steps + 1):
        idx = torch.from_numpy(rng.integers(0, len(data), args.batch))
        s, a, r, s2 = obs[idx], actions[idx], rewards[idx], next_obs[idx]
        # ALGO LOGIC: the TD target from the target network, under no-grad
        with torch.no_grad():
            td_target = r + args.gamma * target(s2).max(dim=1).values  # [B]
        q_all = q(s)  # [B, 5K]
        q_taken = q_all.gather(1, a.unsqueeze(1)).squeeze(1)  # [B]
        td_loss = 0.5 * F.mse_loss(q_taken, td_target)
        # ALGO LOGIC: the conservative term, CQL(H): push down all actions, push up the data's
        cql_loss = (torch.logsumexp(q_all, dim=1) - q_taken).mean()
        loss = td_loss + args.alpha * cql_loss

        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
        if step % args.target_update_every == 0:
            target.load_state_dict(q.state_dict())
        if step % args.log_every == 0 or step == args.total_steps:
            sps = int(step / (time.time() - start))
            print(f"step={step} losses/td_loss={td_loss.item():.4f} "
                  f"losses/cql_loss={cql_loss.item():.4f} "
                  f"losses/q_values={q_taken.mean().item() / args.reward_scale:.1f} charts/SPS={sps}")

    # --- score: the exact evaluation of the tables, and where it lies between random and planner
    score = uavmeta.evaluate(q.act, env)
    normalised = uavmeta.normalised_score(score, env)
    print(f"eval/return={score.ret.mean:.1f} eval/return_ci95={score.ret.ci95:.1f} "
          f"eval/aoi={score.aoi.mean:.3f} eval/power_mw={score.power_mw.mean:.4f} "
          f"eval/outages={score.outages.mean:.2f} eval/trapped_starts={len(score.trapped)}")
    print(f"eval/normalised_score={normalised:.1f} (0 = random, 100 = planner)")
    if args.save:
        q.meta.update(algorithm="cql-python", epoch=args.total_steps)
        save_q_network(q, args.save, world_hash=env._worlds.world_hash, config_toml=env.config_toml)
        print(f"saved {args.save}: uavmeta eval --config {data.config_path} "
              f"--task {data.task_name} --checkpoint {args.save}")


if __name__ == "__main__":
    main()
