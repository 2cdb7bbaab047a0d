"""The PyTorch reference for docs/BENCHMARKS.md: the same computations as
`learner/benches/cql.rs` (`cql_step/bare`) and `meta/benches/maml.rs`, written as a PyTorch user
would, timed the same way (one intra-op thread, median of repeated rounds).

    ~/.cache/uavmeta/torch-2.13.0/bin/python benches/pytorch_reference.py [--population]

Network: K = 10 (12 inputs, 50 actions), hidden [256, 256], PyTorch's default nn.Linear init.
- CQL step (eq. 8): online forward, target forward, TD + conservative loss, backward, Adam, on a
  fixed minibatch of 64 and of 256 rows; with Adam's default (for-loop) implementation on CPU,
  and with `foreach=True` and `fused=True`.
- MAML outer step (Algorithm 4 with one outer step): 8 tasks, each one second-order inner SGD step
  (eq. 14, eta_inner 1e-2) on 64 support shots with the CQL loss and its query loss on 64 query
  shots (eq. 15), then one Adam step on w0 (eq. 16). Two ways: tasks one after another with
  `torch.func.grad` over `functional_call`, and all tasks at once with `torch.func.vmap`.
- `--population`: the stacked steps of `learner/benches/population.rs` (issue #33): N networks
  with weights [N, out, in], one `baddbmm` per layer, each member's mean loss summed, one Adam
  (fused=True) over the stacked tensors; a Double DQN step (Huber, per-member clipping at 10) and
  a CQL step, at N = 1, 8, 32, 80, batch 64 per member; and the floor: the step's `bmm`s alone.
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


def stacked_network(n):
    """N members, each with PyTorch's default nn.Linear init, stacked: [(W [N, out, in], b [N, out])]."""
    members = [network() for _ in range(n)]
    layers = []
    for i in (0, 2, 4):
        w = torch.stack([m[i].weight.detach() for m in members]).requires_grad_()
        b = torch.stack([m[i].bias.detach() for m in members]).requires_grad_()
        layers.append((w, b))
    return layers


def stacked_forward(layers, x):
    for i, (w, b) in enumerate(layers):
        x = torch.baddbmm(b.unsqueeze(1), x, w.transpose(1, 2))
        if i + 1 < len(layers):
            x = x.relu()
    return x


def population_step_seconds(n, dqn):
    q = stacked_network(n)
    target = [(w.detach().clone(), b.detach().clone()) for w, b in q]
    params = [t for layer in q for t in layer]
    optimizer = torch.optim.Adam(params, lr=1e-4, fused=True)
    obs, actions, rewards, next_obs = (torch.stack(c) for c in zip(*[random_batch(64) for _ in range(n)]))

    def step():
        q_all = stacked_forward(q, obs)  # [N, B, A]
        with torch.no_grad():
            next_target = stacked_forward(target, next_obs)
            if dqn:  # Double DQN: the online network's argmax, the target's value
                a_star = stacked_forward(q, next_obs).argmax(-1, keepdim=True)
                next_v = next_target.gather(-1, a_star).squeeze(-1)
            else:
                next_v = next_target.amax(-1)
        y = rewards + GAMMA * next_v
        q_taken = q_all.gather(-1, actions.unsqueeze(-1)).squeeze(-1)
        if dqn:
            loss = F.huber_loss(q_taken, y, reduction="none").mean(-1).sum()
        else:
            td = (q_taken - y).square().mean(-1)
            conservative = (q_all.logsumexp(-1) - q_taken).mean(-1)
            loss = (0.5 * td + ALPHA * conservative).sum()
        optimizer.zero_grad()
        loss.backward()
        if dqn:  # each member's own gradient norm
            norms = torch.stack([p.grad.flatten(1).norm(dim=1) for p in params]).norm(dim=0)
            coef = (10.0 / (norms + 1e-6)).clamp(max=1.0)
            for p in params:
                p.grad.mul_(coef.view(-1, *([1] * (p.dim() - 1))))
        optimizer.step()

    return median_seconds(step, per_round=max(400 // n, 5), rounds=5, warmup=10)


def population_floor_seconds(n, forwards):
    widths = [OBS, HIDDEN, HIDDEN, ACTIONS]
    layers = [(torch.rand(n, 64, i), torch.rand(n, i, o), torch.rand(n, 64, o), torch.rand(n, o, i))
              for i, o in zip(widths, widths[1:])]

    def products():
        for _ in range(forwards):
            for x, wt, _, _ in layers:
                x.bmm(wt)
        for i, (x, _, g, w) in enumerate(layers):
            g.transpose(1, 2).bmm(x)
            if i > 0:
                g.bmm(w)

    return median_seconds(products, per_round=max(400 // n, 5), rounds=5, warmup=10)


def population():
    print("| step | N | step (ms) | learner-steps/s | floor (ms) | of floor |")
    print("| --- | ---: | ---: | ---: | ---: | ---: |")
    for dqn, name, forwards in ((True, "dqn (double, Huber, clip)", 3), (False, "cql (eq. 8)", 2)):
        for n in (1, 8, 32, 80):
            t = population_step_seconds(n, dqn)
            floor = population_floor_seconds(n, forwards)
            print(f"| {name} | {n} | {t * 1e3:.2f} | {n / t:.0f} | {floor * 1e3:.2f} | {100 * floor / t:.0f}% |")
            sys.stdout.flush()


def main():
    print(f"torch {torch.__version__}, {torch.get_num_threads()} intra-op thread")
    if "--population" in sys.argv:
        population()
        return
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
