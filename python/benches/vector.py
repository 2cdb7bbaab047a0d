"""Steps per second of the batched world from Python (docs/BENCHMARKS.md, "The world from
Python"): uavmeta.VectorEnv beside gymnasium.vector.SyncVectorEnv of uavmeta.UavEnv and beside
NumpyWorld, the same world written in a page of numpy, at N = 1, 64 and 4096 envs.

With ``--mixed`` every env runs a task of its own: uavmeta.VectorEnv draws a new task at every
reset from a TaskSampler (lambda in [0, 1000], rain on half the episodes, a third of those
moving; and the same with four device layouts drawn too), SyncVectorEnv runs UavEnvs with the
same sampler, and NumpyWorld holds a fixed mix of lambdas, rain zones and layouts, one per env
(no redraws: the comparison is generous to it); the single-task VectorEnv runs beside them as the
reference.

With ``--team`` the envs are teams of two UAVs (``world.uavs = 2``, two cells a step, the "none"
target, K = 10): uavmeta.TeamVectorEnv beside a loop over uavmeta.pettingzoo.UavTeamEnv (one
PettingZoo ParallelEnv per env, dicts of actions, reset when done), with the one-UAV VectorEnv as
the reference; a team-step is one step of every UAV of one env.

Run on one core, in the virtualenv where the package is installed:

    taskset -c 1 python python/benches/vector.py [--mixed | --team]

Every loop steps with actions drawn beforehand (a pool of up to 64 batches, cycled), so it times
the env alone, for at least --seconds; the three envs take turns, --rounds loops each, and the
table gives the best and the median loop of each.
"""

import argparse
import time

import gymnasium
import numpy as np

import uavmeta

MOVES = np.array([(0, 1), (0, -1), (1, 0), (-1, 0), (0, 0)])


class NumpyWorld:
    """docs/MODEL.md section 1 (defaults, one rain zone, no moving rain) for N envs in numpy, with
    next-step autoreset: the comparison a Python user could write in an afternoon."""

    def __init__(self, n, device_cells, lam, rain=None, grid=10, horizon=100, aoi_max=100,
                 start_cell=None, seed=0, layout_of=None):
        # device_cells: one layout (K, 2), or (L, K, 2) with layout_of giving each env's; lam:
        # one lambda or one per env; rain: one zone, None, or an (n, 4) array of zones (x0 > x1
        # for an env without rain).
        self.n, self.grid, self.horizon, self.aoi_max = n, grid, horizon, aoi_max
        cells = np.asarray(device_cells).reshape(-1, *np.shape(device_cells)[-2:])
        self.layout_of = np.zeros(n, np.int64) if layout_of is None else np.asarray(layout_of)
        self.k = cells.shape[1]
        self.weight = np.asarray(lam, dtype=np.float64) / self.k
        self.rain = None if rain is None else np.asarray(rain).T
        self.start_cell = start_cell
        self.rng = np.random.default_rng(seed)
        # P = (2^(M/B) - 1) sigma^2 / g0 (h^2 + d^2) W, in mW; rain: * 10^(gamma_R d_km / 10).
        xs, ys = np.meshgrid(np.arange(grid), np.arange(grid), indexing="xy")
        ux, uy = xs.reshape(1, -1, 1), ys.reshape(1, -1, 1)  # cell c = y * grid + x
        dx, dy = cells[:, None, :, 0], cells[:, None, :, 1]
        slant2 = 100.0**2 + ((ux - dx) * 100.0) ** 2 + ((uy - dy) * 100.0) ** 2  # (L, cells, K)
        watts_per_m2 = (2.0**5 - 1) * 10 ** (-130 / 10) / 10 ** (-30 / 10)
        self.clear_mw = watts_per_m2 * slant2 * 1e3
        gamma = 0.2051 * 12.5**0.9679
        self.rain_mw = self.clear_mw * 10 ** (gamma * np.sqrt(slant2) / 1e3 / 10)
        self.mw = np.stack([self.clear_mw, self.rain_mw])
        self.rows = np.arange(n)
        self.pending = np.zeros(n, bool)
        self.pos = np.zeros((n, 2), np.int64)
        self.aoi = np.ones((n, self.k), np.int64)
        self.t = np.zeros(n, np.int64)

    def _reset(self, mask):
        m = int(mask.sum())
        if self.start_cell is None:
            self.pos[mask] = self.rng.integers(0, self.grid, (m, 2))
        else:
            self.pos[mask] = self.start_cell
        self.aoi[mask] = 1
        self.t[mask] = 0

    def reset(self):
        self._reset(np.ones(self.n, bool))
        self.pending[:] = False
        return self._obs()

    def _obs(self):
        return np.concatenate([self.pos, self.aoi], axis=1).astype(np.float32)

    def step(self, actions):
        restart = self.pending.copy()
        move, dev = np.divmod(actions, self.k)
        x, y = self.pos[:, 0], self.pos[:, 1]
        cell = y * self.grid + x
        outage = np.zeros(self.n, bool)
        if self.rain is not None:
            x0, y0, x1, y1 = self.rain
            outage = (x0 <= x) & (x <= x1) & (y0 <= y) & (y <= y1)
        table = np.where(outage, 1, 0)  # one gather from the stacked clear and rain tables
        power = self.mw[table, self.layout_of, cell, dev]
        np.minimum(self.aoi + 1, self.aoi_max, out=self.aoi)
        served = ~outage
        self.aoi[self.rows[served], dev[served]] = 1
        reward = -(self.aoi.sum(axis=1) + self.weight * power)
        self.pos += MOVES[move]
        np.clip(self.pos, 0, self.grid - 1, out=self.pos)
        self.t += 1
        truncated = self.t >= self.horizon
        if restart.any():  # next-step autoreset: these envs did not step
            self._reset(restart)
            reward[restart], truncated[restart] = 0.0, False
        self.pending = truncated.copy()
        return self._obs(), reward, np.zeros(self.n, bool), truncated, {}


def check_numpy_world_is_the_world(layouts):
    """Same start, same actions: NumpyWorld's rewards are uavmeta's (so the race is fair), with
    one layout and with a layout per env."""
    ours = uavmeta.VectorEnv(3, lam=300.0, rain=(3, 3, 5, 5), start_cell=[4, 2])
    theirs = NumpyWorld(3, ours.device_cells, 300.0, rain=(3, 3, 5, 5), start_cell=(4, 2))
    same_world(ours, theirs)
    tasks = [dict(lam=300.0, rain=(3, 3, 5, 5), layout=seed) for seed in LAYOUTS[:3]]
    ours = uavmeta.VectorEnv(3, tasks=tasks, start_cell=[4, 2])
    theirs = NumpyWorld(3, layouts[:3], 300.0, rain=(3, 3, 5, 5), start_cell=(4, 2),
                        layout_of=[0, 1, 2])
    same_world(ours, theirs)


def same_world(ours, theirs):
    a, _ = ours.reset(seed=0)
    np.testing.assert_array_equal(a, theirs.reset())
    rng = np.random.default_rng(1)
    for _ in range(250):
        actions = rng.integers(0, 50, 3)
        got, want = ours.step(actions), theirs.step(actions)
        np.testing.assert_array_equal(got[0], want[0])
        np.testing.assert_allclose(got[1], want[1], rtol=1e-12)
        np.testing.assert_array_equal(got[3], want[3])


MIXED = uavmeta.TaskSampler(lam=(0.0, 1000.0), rain_probability=0.5, rain_size=(1, 4),
                            rain_moves_every=(None, None, 10))
LAYOUTS = (None, 1, 2, 3)
MIXED_LAYOUTS = uavmeta.TaskSampler(lam=(0.0, 1000.0), rain_probability=0.5, rain_size=(1, 4),
                                    rain_moves_every=(None, None, 10), layouts=LAYOUTS)


def numpy_mix(n, seed=0):
    """One lambda and one rain zone (or none) per env, as MIXED draws them."""
    rng = np.random.default_rng(seed)
    lam = rng.uniform(0.0, 1000.0, n)
    w, h = rng.integers(1, 5, n), rng.integers(1, 5, n)
    x0, y0 = rng.integers(0, 11 - w), rng.integers(0, 11 - h)
    zones = np.stack([x0, y0, x0 + w - 1, y0 + h - 1], axis=1)
    zones[rng.random(n) >= 0.5] = (1, 1, 0, 0)  # empty: no rain
    return lam, zones


TEAM = dict(lam=300.0, rain=(3, 3, 5, 5), uavs=2, step_cells=2, idle_action=True)


class PettingZooLoop:
    """N UavTeamEnvs stepped one after another with dicts of actions, each reset when its
    agents are done: what a PettingZoo user without a vector env writes."""

    def __init__(self, n):
        from uavmeta.pettingzoo import UavTeamEnv

        self.envs = [UavTeamEnv(**TEAM) for _ in range(n)]
        self.agents = self.envs[0].possible_agents

    def reset(self, seed=0):
        for i, env in enumerate(self.envs):
            env.reset(seed=seed + i)

    def step(self, actions):
        for env, acts in zip(self.envs, actions):
            if not env.agents:
                env.reset()
            else:
                env.step(dict(zip(self.agents, acts.tolist())))


def rate(env, pool, seconds):
    """Env steps per second of one loop of at least ``seconds``."""
    n = pool.shape[1]
    steps, start = 0, time.perf_counter()
    while True:
        for actions in pool:
            env.step(actions)
            steps += 1
        elapsed = time.perf_counter() - start
        if elapsed >= seconds:
            return steps * n / elapsed


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[1, 64, 4096])
    parser.add_argument("--seconds", type=float, default=0.5, help="per loop")
    parser.add_argument("--rounds", type=int, default=7, help="loops per env, interleaved")
    parser.add_argument("--mixed", action="store_true", help="a task per env (module doc)")
    parser.add_argument("--team", action="store_true", help="teams of two UAVs (module doc)")
    args = parser.parse_args()
    cells = uavmeta.UavEnv(lam=300.0).device_cells
    layouts = [
        uavmeta.VectorEnv(1, tasks=[dict(lam=0.0, layout=seed)]).task_of(0)["device_cells"]
        for seed in LAYOUTS
    ]
    check_numpy_world_is_the_world(layouts)
    makers = {
        "uavmeta.VectorEnv": lambda n: uavmeta.VectorEnv(n, lam=300.0, rain=(3, 3, 5, 5)),
        "SyncVectorEnv(UavEnv)": lambda n: gymnasium.vector.SyncVectorEnv(
            [lambda: uavmeta.UavEnv(lam=300.0, rain=(3, 3, 5, 5)) for _ in range(n)]
        ),
        "NumpyWorld": lambda n: NumpyWorld(
            n, uavmeta.UavEnv(lam=300.0).device_cells, 300.0, rain=(3, 3, 5, 5)
        ),
    }
    if args.mixed:
        makers = {
            "uavmeta.VectorEnv, one task": makers["uavmeta.VectorEnv"],
            "uavmeta.VectorEnv, TaskSampler": lambda n: uavmeta.VectorEnv(n, tasks=MIXED),
            "SyncVectorEnv(UavEnv), TaskSampler": lambda n: gymnasium.vector.SyncVectorEnv(
                [lambda: uavmeta.UavEnv(tasks=MIXED) for _ in range(n)]
            ),
            "NumpyWorld, a task per env": lambda n: NumpyWorld(n, cells, *numpy_mix(n)),
            "uavmeta.VectorEnv, TaskSampler, 4 layouts": lambda n: uavmeta.VectorEnv(
                n, tasks=MIXED_LAYOUTS
            ),
            "NumpyWorld, a task and a layout per env": lambda n: NumpyWorld(
                n, layouts, *numpy_mix(n), layout_of=np.arange(n) % len(LAYOUTS)
            ),
        }
    shapes = {name: () for name in makers}
    if args.team:
        team_actions = uavmeta.TeamVectorEnv(1, **TEAM).single_action_space.n
        makers = {
            "uavmeta.TeamVectorEnv, 2 UAVs": lambda n: uavmeta.TeamVectorEnv(n, **TEAM),
            "a loop of UavTeamEnv (PettingZoo), 2 UAVs": PettingZooLoop,
            "uavmeta.VectorEnv, 1 UAV": makers["uavmeta.VectorEnv"],
        }
        shapes = {name: (2,) for name in makers}
        shapes["uavmeta.VectorEnv, 1 UAV"] = ()
    results = {name: [] for name in makers}
    for n in args.sizes:
        envs = {name: make(n) for name, make in makers.items()}
        for env in envs.values():
            env.reset(seed=0) if not isinstance(env, NumpyWorld) else env.reset()
        batches = max(1, min(64, 4096 // n))
        pools = {
            name: np.random.default_rng(0).integers(
                0, team_actions if shapes[name] else 50, (batches, n, *shapes[name])
            )
            for name in makers
        }
        rates = {name: [] for name in makers}
        # Interleaved, so that a burst of load elsewhere on the machine hits every env alike.
        for _ in range(args.rounds):
            for name, env in envs.items():
                rates[name].append(rate(env, pools[name], args.seconds))
        for name in makers:
            results[name].append((max(rates[name]), float(np.median(rates[name]))))
    unit = "team-steps/s (one UAV's steps/s for VectorEnv)" if args.team else "env steps/s"
    print("best (median) of", args.rounds, "interleaved loops of", args.seconds, "s,", unit)
    print("| env | " + " | ".join(f"N = {n}" for n in args.sizes) + " |")
    print("| --- |" + " ---: |" * len(args.sizes))
    for name, cells in results.items():
        print(f"| {name} | " + " | ".join(f"{fmt(b)} ({fmt(m)})" for b, m in cells) + " |")


def fmt(rate):
    return f"{rate / 1e6:.2f} M" if rate >= 1e6 else f"{rate / 1e3:.0f} k"


if __name__ == "__main__":
    main()
