"""uavmeta.policies.checkpoint: a Q-network that `uavmeta train` saved, run in numpy, against the
CLI's `--policy q:EPSILON:PATH` and against damaged or mismatched checkpoints."""

import shutil
import subprocess
import sys

import numpy as np
import pytest

import uavmeta
from conftest import CONFIG, REPO
from test_env import assert_same_steps, trace


@pytest.mark.parametrize("normalised", [False, True])
def test_the_greedy_policy_chooses_what_the_cli_chooses(run_cli, tmp_path, trained, normalised):
    steps = trace(run_cli, tmp_path, 3, 4, f"q:0:{trained}", "--task", "lambda-300")
    assert len(steps) == 300 and len({s["action"] for s in steps}) >= 10
    env = uavmeta.UavEnv.from_config(CONFIG, task="lambda-300", normalised=normalised)
    policy = uavmeta.policies.checkpoint(env, trained)
    assert_same_steps(env, steps, lambda obs, s: policy(obs), seed=4)
    stalest = uavmeta.policies.stalest(env)
    assert any(stalest(policy_obs) != policy(policy_obs) for policy_obs in _observations(env))


def test_a_bcq_network_acts_on_the_actions_its_imitation_head_supports(run_cli, tmp_path, trained_bcq):
    steps = trace(run_cli, tmp_path, 3, 4, f"q:0:{trained_bcq}", "--task", "lambda-300")
    env = uavmeta.UavEnv.from_config(CONFIG, task="lambda-300", normalised=True)
    policy = uavmeta.policies.checkpoint(env, trained_bcq)
    assert policy.outputs(np.zeros(12, np.float32)).shape == (100,)
    assert policy.q_values(np.zeros(12, np.float32)).shape == (50,)
    assert_same_steps(env, steps, lambda obs, s: policy(obs), seed=4)
    net = uavmeta.nn.load_q_network(trained_bcq)
    obs = np.stack(_observations(env, 20))
    assert (net.act(obs) == policy(obs)).all()
    # The rule itself: Q = [1, 2, 3], logits [0, 2, 2]: action 0 is 0.14 as likely as the best,
    # below tau = 0.3, so the greedy action is 2; with logits [0, 3, 1] only action 1 is left.
    out = np.array([[1, 2, 3, 0, 2, 2], [0, -1, 4, 0, 3, 1]], np.float32)
    assert uavmeta.policies.bcq_supported_values(out, 0.3).argmax(axis=1).tolist() == [2, 1]
    assert uavmeta.policies.bcq_supported_values(out, 0.0).argmax(axis=1).tolist() == [2, 2]


def _observations(env, n=50):
    obs, _ = env.reset(seed=0)
    rows = []
    for _ in range(n):
        rows.append(obs)
        obs, *_ = env.step(env.action_space.sample())
    return rows


def test_a_batch_equals_one_row_at_a_time_and_make_reads_the_cli_spec(trained):
    env = uavmeta.VectorEnv(32, config=CONFIG, lam=300.0, normalised=True)
    obs, _ = env.reset(seed=1)
    for _ in range(20):
        obs, *_ = env.step(env.action_space.sample())
    policy = uavmeta.policies.make(f"q:0:{trained}", env)
    batch = policy(obs)
    assert batch.dtype == np.int64 and batch.shape == (32,)
    assert batch.tolist() == [policy(row) for row in obs]
    q = policy.q_values(obs)
    assert q.shape == (32, 50) and q.dtype == np.float32
    assert batch.tolist() == q.argmax(axis=1).tolist()


def test_epsilon_one_is_uniform_and_seeded(trained):
    env = uavmeta.VectorEnv(5000, config=CONFIG, lam=300.0)
    obs, _ = env.reset(seed=2)
    a = uavmeta.policies.checkpoint(env, trained, epsilon=1.0, seed=9)(obs)
    b = uavmeta.policies.checkpoint(env, trained, epsilon=1.0, seed=9)(obs)
    greedy = uavmeta.policies.checkpoint(env, trained)(obs)
    assert a.tolist() == b.tolist()
    counts = np.bincount(a, minlength=50)
    # 5000 uniform draws over 50 actions: 100 each, a count outside 50-150 is 5 sigma away.
    assert counts.min() >= 50 and counts.max() <= 150, counts
    assert len(set(greedy.tolist())) < 50


def test_bad_checkpoints_and_arguments_raise_naming_them(trained, tmp_path):
    env = uavmeta.UavEnv(config=CONFIG, lam=300.0)
    with pytest.raises(ValueError, match=r"nowhere\.json"):
        uavmeta.policies.checkpoint(env, tmp_path / "nowhere")
    with pytest.raises(ValueError, match=r"epsilon = 1\.5"):
        uavmeta.policies.checkpoint(env, trained, epsilon=1.5)
    with pytest.raises(ValueError, match="q:EPSILON:PATH"):
        uavmeta.policies.make(f"q:x:{trained}", env)
    small = uavmeta.UavEnv(config=CONFIG, lam=300.0, devices=4)
    with pytest.raises(ValueError, match=r"obs_len = 12.*world\.devices = 4"):
        uavmeta.policies.checkpoint(small, trained)

    damaged = tmp_path / "damaged"
    shutil.copy(f"{trained}.json", f"{damaged}.json")
    weights = bytearray(open(f"{trained}.safetensors", "rb").read())
    weights[-7] ^= 0x40
    open(f"{damaged}.safetensors", "wb").write(weights)
    with pytest.raises(ValueError, match=r"damaged\.safetensors.*CRC32"):
        uavmeta.policies.checkpoint(env, damaged)

    other_world = uavmeta.UavEnv(config=CONFIG, lam=300.0, layout_seed=8)
    with pytest.warns(UserWarning, match="another world"):
        uavmeta.policies.checkpoint(other_world, trained)


def test_the_quickstart_runs_a_checkpoint(trained, tmp_path):
    out = subprocess.run(
        [sys.executable, str(REPO / "examples" / "python_quickstart.py"),
         "--checkpoint", str(trained)],
        capture_output=True, text=True, cwd=tmp_path,
    )
    assert out.returncode == 0, out.stderr
    assert f"{trained}: return" in out.stdout, out.stdout
