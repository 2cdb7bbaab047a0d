"""The PyTorch reference for docs/BENCHMARKS.md: the same computations as
`learner/benches/cql.rs` (`cql_step/bare`) and `meta/benches/maml.rs`, written as a PyTorch user
would, timed the same way (one intra-op thread, median of repeated rounds).

    ~/.cache/uavmeta/torch-2.13.0/bin/python benches/pytorch_reference.py

Network: K = 10 (12 inputs, 50 actions), hidden [256, 256], PyTorch's default nn.Linear init.
- CQL step (eq. 8): online forward, target forward, TD + conservative loss, backward, Adam, on a
  fixed minibatch of 64 and of 256 rows; with Adam's default (for-loop) implementation on CPU,
  and with `foreach=True` and `fused=True`.
- MAML outer step (Algorithm 4 with one outer step): 8 tasks, each one second-order inner SGD step
  (eq. 14, eta_inner 1e-2) on 64 support shots with the CQL loss and its query loss on 64 query
  shots (eq. 15), then one Adam step on w0 (eq. 16). Two ways: tasks one after another with
  `torch.func.grad` over `functional_call`, and all tasks at once with `torch.func.vmap`.
"""

import statistics
import sys
import time

import torch
import torch.nn as nn
import torch.nn.functional as F
from torch.func import functional_call, grad, vmap

torch.set_num_threads(1)
torch.manual_seed(0)

OBS, ACTIONS, HIDDEN = 12, 50, 256
GAMMA, ALPHA, ETA_INNER = 0.99, 1.0, 1e-2


def network():
    return nn.Sequential(
        nn.Linear(OBS, HIDDEN), nn.ReLU(),
        nn.Linear(HIDDEN, HIDDEN), nn.ReLU(),
        nn.Linear(HIDDEN, ACTIONS),
    )


def random_batch(rows):
    return (
        torch.rand(rows, OBS),
        torch.randint(ACTIONS, (rows,)),
        -torch.rand(rows),
        torch.rand(rows, OBS),
    )


def median_seconds(step, per_round, rounds=7, warmup=20):
    """Median over `rounds` of the mean time of `per_round` calls."""
    for _ in range(warmup):
        step()
    times = []
    for _ in range(rounds):
        start = time.perf_counter()
        for _ in range(per_round):
            step()
        times.append((time.perf_counter() - start) / per_round)
    return statistics.median(times)


def cql_loss(q_all, next_q_target, actions, rewards):
    """Eq. 8: 0.5 * eq. 7 + alpha * mean(logsumexp_a Q(s, a) - Q(s, a_data))."""
    y = rewards + GAMMA * next_q_target.amax(-1)
    q_taken = q_all.gather(-1, actions.unsqueeze(-1)).squeeze(-1)
    td = F.mse_loss(q_taken, y)
    conservative = (q_all.logsumexp(-1) - q_taken).mean()
    return 0.5 * td + ALPHA * conservative


def cql_step_seconds(batch, adam):
    q, target = network(), network()
    target.load_state_dict(q.state_dict())
    optimizer = torch.optim.Adam(q.parameters(), lr=1e-3, **adam)
    obs, actions, rewards, next_obs = random_batch(batch)

    def step():
        q_all = q(obs)
        with torch.no_grad():
            next_q = target(next_obs)
        loss = cql_loss(q_all, next_q, actions, rewards)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()

    return median_seconds(step, per_round=200)


def maml_seconds(batched, tasks=8, shots=64):
    w0_net = network()
    target = {k: v.detach().clone() for k, v in w0_net.named_parameters()}
    w0 = dict(w0_net.named_parameters())
    optimizer = torch.optim.Adam(w0.values(), lr=1e-3)
    support = [random_batch(shots) for _ in range(tasks)]
    query = [random_batch(shots) for _ in range(tasks)]

    def task_loss(params, batch):
        obs, actions, rewards, next_obs = batch
        q_all = functional_call(w0_net, params, (obs,))
        next_q = functional_call(w0_net, target, (next_obs,)).detach()
        return cql_loss(q_all, next_q, actions, rewards)

    def adapted_query_loss(params, support_batch, query_batch):
        # eq. 14, second order: torch.func.grad keeps the graph back to params.
        g = grad(task_loss)(params, support_batch)
        fast = {k: params[k] - ETA_INNER * g[k] for k in params}
        return task_loss(fast, query_batch)  # a term of eq. 15

    stacked_support = tuple(torch.stack(col) for col in zip(*support))
    stacked_query = tuple(torch.stack(col) for col in zip(*query))

    def step():
        optimizer.zero_grad()
        if batched:
            losses = vmap(adapted_query_loss, in_dims=(None, 0, 0))(
                w0, stacked_support, stacked_query)
            losses.sum().backward()
        else:
            for s, q in zip(support, query):
                adapted_query_loss(w0, s, q).backward()
        optimizer.step()  # eq. 16

    return median_seconds(step, per_round=10, rounds=7, warmup=3)


def main():
    print(f"torch {torch.__version__}, {torch.get_num_threads()} intra-op thread")
    for batch in (64, 256):
        for name, adam in (("default", {}), ("foreach", {"foreach": True}), ("fused", {"fused": True})):
            ms = cql_step_seconds(batch, adam) * 1e3
            print(f"cql_step batch {batch} adam {name}: {ms:.3f} ms")
    for batched in (False, True):
        how = "vmap over tasks" if batched else "task by task"
        s = maml_seconds(batched)
        print(f"maml outer step, 8 tasks, 1 second-order inner step, {how}: {s * 1e3:.1f} ms")
    sys.stdout.flush()


if __name__ == "__main__":
    main()
