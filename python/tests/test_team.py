"""The team's world from Python (docs/MODEL.md section 11): PettingZoo's own API test on
UavTeamEnv, TeamVectorEnv against N UavTeamEnvs, the team's reward recomputed from what the env
reports, and every bad argument named."""

import numpy as np
import pytest
from pettingzoo.test import parallel_api_test

import uavmeta
from uavmeta.pettingzoo import UavTeamEnv, parallel_env

# The authors' team: two UAVs of two-cell moves, each free to serve no device.
TEAM = dict(uavs=2, step_cells=2, idle_action=True)


@pytest.mark.parametrize(
    "kwargs",
    [dict(TEAM, lam=300.0), dict(uavs=3, lam=700.0, rain=(1, 1, 4, 6), horizon=30, normalised=True),
     dict(lam=300.0)],
)
def test_pettingzoo_parallel_api_test_passes(kwargs):
    parallel_api_test(parallel_env(**kwargs), num_cycles=300)


def random_actions(rng, agents, count):
    return {a: int(rng.integers(count)) for a in agents}


def test_observations_are_each_uavs_view_of_the_state_and_the_reward_is_the_teams():
    env = parallel_env(**TEAM, lam=300.0)
    k, u = env.devices, len(env.possible_agents)
    assert env.possible_agents == ["uav_0", "uav_1"]
    assert env.action_space("uav_1").n == 5 * (k + 1)
    assert env.state_space.shape == (2 * u + k,)
    obs, infos = env.reset(seed=3)
    rng, idle_steps, served = np.random.default_rng(0), 0, set()
    while env.agents:
        state = env.state()
        assert env.state_space.contains(state)
        for i, agent in enumerate(env.possible_agents):
            np.testing.assert_array_equal(obs[agent][:2], state[2 * i : 2 * i + 2])
            np.testing.assert_array_equal(obs[agent][2:], state[2 * u :])
        actions = random_actions(rng, env.agents, env.action_space("uav_0").n)
        obs, rewards, terms, truncs, infos = env.step(actions)
        after = env.state()
        # -(sum_j A_j + lambda / K * the team's power): one reward for every agent.
        expected = -(after[2 * u :].sum() + 300.0 / k * infos["uav_0"]["power_mw"])
        assert len(set(rewards.values())) == 1
        assert rewards["uav_0"] == pytest.approx(expected, rel=1e-6)  # the state is float32
        targets = [infos[a]["target"] for a in env.possible_agents]
        assert targets == [actions[a] % (k + 1) for a in env.possible_agents]
        idle_steps += targets.count(k)
        served.update(t for t in targets if t < k)
        # Two-cell moves: each UAV moved by 0 or 2 cells, or stopped at the grid's edge.
        assert not any(terms.values())
    assert idle_steps > 0 and served == set(range(k))
    with pytest.raises(uavmeta.ResetNeeded):
        env.step({})


def test_both_uavs_serving_one_device_restart_it_once_and_pay_both():
    env = parallel_env(**TEAM, lam=300.0, start_cell=[0, 0])
    env.reset(seed=1)
    hover = uavmeta.MOVES.index("hover") * (env.devices + 1)
    _, _, _, _, alone = env.step({"uav_0": hover + 4, "uav_1": hover + env.devices})
    env.reset(seed=1)
    _, _, _, _, both = env.step({"uav_0": hover + 4, "uav_1": hover + 4})
    assert env.state()[4 + 4] == 1
    assert both["uav_0"]["power_mw"] == pytest.approx(2 * alone["uav_0"]["power_mw"])


def test_seeds_replay_and_the_vector_env_equals_single_team_envs():
    n, rng = 3, np.random.default_rng(5)
    ours = uavmeta.TeamVectorEnv(n, **TEAM, lam=500.0, rain=(2, 2, 5, 5), horizon=12)
    singles = [UavTeamEnv(**TEAM, lam=500.0, rain=(2, 2, 5, 5), horizon=12) for _ in range(n)]
    obs, infos = ours.reset(seed=40)
    for i, env in enumerate(singles):
        o, _ = env.reset(seed=40 + i)
        np.testing.assert_array_equal(obs[i], np.stack([o[a] for a in env.possible_agents]))
        np.testing.assert_array_equal(infos["state"][i], env.state())
    outages = 0
    for step in range(30):  # two autoresets: the vector env resets env i, a single env is reset
        actions = rng.integers(ours.single_action_space.n, size=(n, 2))
        obs, reward, _, truncated, infos = ours.step(actions)
        for i, env in enumerate(singles):
            if not env.agents:
                # No step info for a resetting env (no key at all when every env reset).
                assert not infos.get("_aoi", np.zeros(n, bool))[i] and reward[i] == 0.0
                o, _ = env.reset()
            else:
                o, r, _, t, inf = env.step(dict(zip(env.possible_agents, map(int, actions[i]))))
                assert (reward[i], truncated[i]) == (r["uav_0"], t["uav_0"])
                assert infos["outages"][i] == inf["uav_0"]["outages"]
                outages += infos["outages"][i]
            np.testing.assert_array_equal(obs[i], np.stack([o[a] for a in env.possible_agents]))
            np.testing.assert_array_equal(infos["state"][i], env.state())
    assert outages > 0  # the rain zone was flown through


@pytest.mark.parametrize(
    "call, error, message",
    [
        (lambda: uavmeta.UavEnv(uavs=2), ValueError, "world.uavs = 2: UavEnv flies one UAV"),
        (lambda: uavmeta.VectorEnv(4, uavs=2), ValueError, "world.uavs = 2: VectorEnv flies one UAV"),
        (lambda: parallel_env(uavs=9), ValueError, "world.uavs"),
        (lambda: parallel_env(uavs=0), ValueError, "world.uavs"),
        (lambda: parallel_env(**TEAM, render_mode="human"), ValueError, "render_mode = 'human'"),
    ],
)
def test_a_bad_team_argument_is_named(call, error, message):
    with pytest.raises(error, match=message):
        call()


def test_a_bad_action_is_named():
    env = parallel_env(**TEAM)
    with pytest.raises(uavmeta.ResetNeeded):
        env.step({"uav_0": 0, "uav_1": 0})
    with pytest.raises(uavmeta.ResetNeeded, match="state"):
        env.state()
    env.reset(seed=0)
    with pytest.raises(ValueError, match="lack 'uav_1'"):
        env.step({"uav_0": 0})
    with pytest.raises(ValueError, match="'uav_7'"):
        env.step({"uav_0": 0, "uav_1": 0, "uav_7": 0})
    with pytest.raises(ValueError, match="action = 55: expected an action index in 0..55"):
        env.step({"uav_0": 55, "uav_1": 0})
    with pytest.raises(TypeError, match="action = 1.5"):
        env.step({"uav_0": 1.5, "uav_1": 0})
    with pytest.raises(TypeError, match="expected a dict"):
        env.step([0, 0])
    with pytest.raises(KeyError, match="'uav_2'"):
        env.observation_space("uav_2")
    vec = uavmeta.TeamVectorEnv(2, **TEAM)
    with pytest.raises(uavmeta.ResetNeeded):
        vec.step(np.zeros((2, 2), np.int64))
    vec.reset(seed=0)
    with pytest.raises(ValueError, match=r"shape \(2,\): expected \(2, 2\)"):
        vec.step(np.zeros(2, np.int64))
    with pytest.raises(ValueError, match=r"actions\[1, 0\] = -1"):
        vec.step(np.array([[0, 0], [-1, 0]]))
    with pytest.raises(ValueError, match=r"actions\[0, 1\] = 99"):
        vec.step(np.array([[0, 99], [0, 0]], np.uint64))
