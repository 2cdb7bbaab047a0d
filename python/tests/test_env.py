"""UavEnv as Gymnasium's checker, the CLI's traces and a user's bad arguments see it."""

import json
import re

import gymnasium
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import uavmeta
from conftest import CONFIG


@pytest.mark.parametrize("normalised", [False, True])
def test_check_env_passes(normalised):
    env = gymnasium.make(uavmeta.ENV_ID, lam=300.0, rain=(3, 3, 5, 5), normalised=normalised)
    check_env(env.unwrapped, skip_render_check=False)


def test_make_and_from_config_build_the_named_task():
    env = gymnasium.make("uavmeta/UAV-v0", lam=300.0)
    assert env.unwrapped.lam == 300.0
    assert env.observation_space.shape == (12,) and env.action_space.n == 50
    named = uavmeta.UavEnv.from_config(CONFIG, task="lambda-300")
    assert named.task_name == "lambda-300" and named.lam == 300.0
    small = uavmeta.UavEnv(lam=0.0, devices=4, grid_cells=6, horizon=7)
    assert small.observation_space.shape == (6,) and small.action_space.n == 20
    obs, _ = small.reset(seed=1)
    for t in range(7):
        obs, _, terminated, truncated, _ = small.step(small.action_space.sample())
        assert not terminated and truncated == (t == 6)
    with pytest.raises(RuntimeError, match="reset"):
        small.step(0)


def test_observations_are_raw_or_normalised():
    raw = uavmeta.UavEnv(lam=300.0)
    norm = uavmeta.UavEnv(lam=300.0, normalised=True)
    a, _ = raw.reset(seed=5)
    b, _ = norm.reset(seed=5)
    scale = np.array([9, 9] + [100] * 10, dtype=np.float32)
    np.testing.assert_allclose(a / scale, b, rtol=1e-6)
    assert np.all(a[2:] == 1) and a.dtype == np.float32


def trace(run_cli, tmp_path, episodes, seed, policy, *task):
    """The CLI's per-step trace lines of a rollout."""
    out = run_cli(
        "env", "rollout", "--config", CONFIG, *task, "--policy", policy,
        "--episodes", episodes, "--seed", seed, "--trace",
    )
    return [json.loads(line) for line in out.stdout.splitlines()]


def assert_same_steps(env, steps, act, seed):
    """Runs env from reset(seed) through the CLI's steps, choosing each action with act(obs, step)
    and checking every step's cell, reward, AoI, power, outage and device."""
    worlds = env.unwrapped._worlds
    scale = np.array(worlds.observation_scale) if worlds.normalised else np.ones(2 + env.devices)
    obs, _ = env.reset(seed=seed)
    episode = 0
    for s in steps:
        if s["episode"] != episode:
            episode = s["episode"]
            obs, _ = env.reset()
        assert list(env.uav) == s["position"], s
        action = act(obs, s)
        assert action == s["action"], s
        obs, reward, terminated, truncated, info = env.step(action)
        assert reward == s["reward"], s
        assert info["power_mw"] == s["power_mw"] and info["outage"] == s["outage"], s
        assert info["device"] == s["device"], s
        assert np.rint(obs[2:] * scale[2:]).astype(int).tolist() == s["aoi"], s
        assert info["aoi"] == pytest.approx(np.mean(s["aoi"]), rel=1e-12)
        assert not terminated and truncated == (s["t"] == env.horizon - 1)


def test_a_fixed_action_sequence_gives_the_cli_trace(run_cli, tmp_path):
    actions = np.random.default_rng(17).integers(0, 50, size=300)
    file = tmp_path / "actions.txt"
    file.write_text("\n".join(map(str, actions)) + "\n")
    steps = trace(run_cli, tmp_path, 3, 7, f"actions:{file}", "--lambda", "300", "--rain", "3,3,5,5")
    assert len(steps) == 300 and any(s["outage"] for s in steps)
    env = uavmeta.UavEnv(config=CONFIG, lam=300.0, rain=(3, 3, 5, 5))
    replay = iter(actions.tolist())
    assert_same_steps(env, steps, lambda obs, s: next(replay), seed=7)


def test_a_moving_rain_zone_moves_as_in_the_cli(run_cli, tmp_path):
    config = tmp_path / "moving.toml"
    config.write_text(
        CONFIG.read_text()
        + '\n[[tasks]]\nname = "moving"\nlambda = 500.0\nrole = "meta-test"\n'
        + "rain = { x0 = 2, y0 = 2, x1 = 6, y1 = 5 }\nrain_moves_every = 3\n"
    )
    out = run_cli(
        "env", "rollout", "--config", config, "--task", "moving", "--policy", "random",
        "--episodes", 2, "--seed", 12, "--trace",
    )
    steps = [json.loads(line) for line in out.stdout.splitlines()]
    env = uavmeta.UavEnv.from_config(config, task="moving")
    policy = uavmeta.policies.random(env, seed=12)
    assert_same_steps(env, steps, lambda obs, s: policy(obs), seed=12)


@pytest.mark.parametrize("name", ["stalest", "greedy"])
def test_heuristics_choose_what_the_cli_chooses(run_cli, tmp_path, name):
    steps = trace(run_cli, tmp_path, 2, 4, name, "--lambda", "200", "--rain", "0,0,4,9")
    for normalised in (False, True):
        env = uavmeta.UavEnv(config=CONFIG, lam=200.0, rain=(0, 0, 4, 9), normalised=normalised)
        policy = uavmeta.policies.make(name, env)
        assert_same_steps(env, steps, lambda obs, s: policy(obs), seed=4)


def test_the_planner_chooses_what_the_cli_chooses(run_cli, tmp_path):
    steps = trace(run_cli, tmp_path, 2, 4, "planner", "--lambda", "600")
    env = uavmeta.UavEnv(config=CONFIG, lam=600.0)
    policy = uavmeta.policies.planner(env)
    assert_same_steps(env, steps, lambda obs, s: policy(obs, t=env.t), seed=4)
    with pytest.raises(ValueError, match="t = 100"):
        policy(env.reset(seed=0)[0], t=100)


def test_batched_heuristics_equal_one_row_at_a_time():
    env = uavmeta.VectorEnv(16, lam=300.0)
    obs, _ = env.reset(seed=0)
    for _ in range(30):
        obs, *_ = env.step(env.action_space.sample())
    for name in ("stalest", "greedy"):
        policy = uavmeta.policies.make(name, env)
        batch = policy(obs)
        assert batch.dtype == np.int64 and batch.shape == (16,)
        assert batch.tolist() == [policy(row) for row in obs]


@pytest.mark.parametrize(
    "kwargs, needle",
    [
        (dict(lam=float("nan")), "lam = NaN"),
        (dict(lam=-1.0), "lam = -1.0"),
        (dict(lam=300.0, rain=(8, 8, 12, 12)), "rain = (8, 8, 12, 12)"),
        (dict(lam=300.0, rain=(-1, 0, 2, 2)), "rain = (-1, 0, 2, 2)"),
        (dict(lam=300.0, rain=(1, 1, 2, 2), rain_moves_every=0), "rain_moves_every = 0"),
        (dict(colour="red"), "world.colour"),
        (dict(devices=0), "world.devices"),
        (dict(set=["learner.nonsense=1"]), "nonsense"),
        (dict(set=["world.uavs=2"]), "world.uavs"),
        (dict(set=["world.uavs=0"]), "world.uavs"),
        (dict(config=CONFIG, task="lambda-301"), "lambda-301"),
        (dict(config=CONFIG, task="lambda-300", lam=3.0), "task = 'lambda-300' and lam = 3.0"),
    ],
)
def test_bad_arguments_raise_value_errors_naming_them(kwargs, needle):
    with pytest.raises(ValueError) as error:
        uavmeta.UavEnv(**kwargs)
    assert needle.replace("'", '"') in str(error.value).replace("'", '"'), str(error.value)


@pytest.mark.parametrize(
    "action, error",
    [(50, ValueError), (-1, ValueError), (np.uint64(2**63), ValueError), (3.5, TypeError),
     ("north", TypeError), (None, TypeError), (True, TypeError)],
)
def test_a_bad_action_raises_an_error_naming_it(action, error):
    env = uavmeta.UavEnv(lam=300.0)
    env.reset(seed=0)
    with pytest.raises(error, match=re.escape(f"action = {action!r}")):
        env.step(action)
    env.step(np.int64(49))  # the env is still usable


def test_bad_seeds_raise_errors_naming_them():
    env = uavmeta.UavEnv(lam=300.0)
    with pytest.raises(ValueError, match="seed = -1"):
        env.reset(seed=-1)
    with pytest.raises(TypeError, match="seed = 1.5"):
        env.reset(seed=1.5)


def test_step_before_reset_is_refused():
    env = uavmeta.UavEnv(lam=300.0)
    with pytest.raises(uavmeta.ResetNeeded, match="reset"):
        env.step(0)


@pytest.mark.parametrize(
    "kwargs, error, needle",
    [
        (dict(set="world.devices=5"), TypeError, "set = 'world.devices=5': expected a list"),
        (dict(set=["world.devices"]), ValueError, "set[0] = 'world.devices'"),
        (dict(set=[5]), TypeError, "set[0] = 5"),
        (dict(config="no/such/config.toml"), FileNotFoundError, 'config = "no/such/config.toml"'),
        (dict(config=3), TypeError, "config = 3"),
        (dict(lam="300"), TypeError, "lam = '300'"),
        (dict(task=300), TypeError, "task = 300"),
        (dict(rain=5), TypeError, "rain = 5"),
        (dict(rain=(1, 1, 2.5, 3)), TypeError, "rain = (1, 1, 2.5, 3)"),
        (dict(normalised="yes"), TypeError, "normalised = 'yes'"),
        (dict(horizon=object()), TypeError, "world.horizon"),
    ],
)
def test_bad_argument_types_raise_the_right_error_naming_them(kwargs, error, needle):
    with pytest.raises(error) as e:
        uavmeta.UavEnv(**kwargs)
    assert needle in str(e.value), str(e.value)


def test_the_planners_step_must_be_a_step_of_the_episode():
    env = uavmeta.UavEnv(lam=300.0)
    obs, _ = env.reset(seed=0)
    plan = uavmeta.policies.planner(env)
    with pytest.raises(ValueError, match="t = -1: expected a step of the episode, 0..100"):
        plan(obs, t=-1)
    with pytest.raises(TypeError, match="t = 2.0"):
        plan(obs, t=2.0)
    assert 0 <= plan(obs, t=np.int64(0)) < 50


def test_reset_is_deterministic_and_episodes_follow_the_seed():
    env = uavmeta.UavEnv(lam=300.0)
    first = [env.reset(seed=3)[0]] + [env.reset()[0] for _ in range(20)]
    again = [env.reset(seed=3)[0]] + [env.reset()[0] for _ in range(20)]
    np.testing.assert_array_equal(first, again)
    starts = {tuple(o[:2]) for o in first}
    assert len(starts) > 5  # episodes start in different cells


def test_render_draws_the_grid_rain_devices_and_uav():
    env = uavmeta.UavEnv(lam=300.0, rain=(0, 0, 2, 2), start_cell=[7, 7])
    env.reset(seed=0)
    for _ in range(3):
        env.step(3 * env.devices)  # west, device 0
    frame = env.render()
    px = uavmeta.render.cell_pixels(10)
    assert frame.shape == (10 * px + 1, 10 * px + 1, 3) and frame.dtype == np.uint8

    def pixel(x, y, dx=0, dy=0):  # near the centre of cell (x, y), north up
        return tuple(frame[(9 - y) * px + px // 2 + dy, x * px + px // 2 + dx])

    assert env.uav == (4, 7)
    assert pixel(4, 7) == uavmeta.render.UAV
    assert pixel(6, 7) == uavmeta.render.PATH  # the path flown
    assert pixel(1, 1, dx=px // 3, dy=px // 3) in (uavmeta.render.RAIN,) or (1, 1) in env.device_cells
    for x, y in env.device_cells:
        assert pixel(x, y, dx=1) not in (uavmeta.render.BACKGROUND, uavmeta.render.RAIN)
    picture = uavmeta.render.trajectory(env, [(0, 0), (0, 1), (1, 1)])
    assert picture.shape == frame.shape


def test_action_indices_are_move_times_k_plus_device():
    assert uavmeta.MOVES == ("north", "south", "east", "west", "hover")
    assert uavmeta.action("west", 4) == 34 and uavmeta.action_parts(34) == ("west", 4)
    assert uavmeta.action("hover", 2, devices=5) == 22
    env = uavmeta.UavEnv(lam=300.0, start_cell=[5, 5])
    env.reset(seed=0)
    for move, cell in [("north", (5, 6)), ("east", (6, 6)), ("south", (6, 5)), ("west", (5, 5))]:
        _, _, _, _, info = env.step(uavmeta.action(move, 7))
        assert env.uav == cell and info["device"] == 7
    with pytest.raises(ValueError, match="move = 'up'"):
        uavmeta.action("up", 0)
