"""load_dataset on a file that `uavmeta collect` wrote, and on damaged files."""

import numpy as np
import pytest

import uavmeta
from conftest import CONFIG

HORIZON = 20


@pytest.fixture(scope="module")
def collected(run_cli, tmp_path_factory):
    """200 transitions (10 episodes) of the random policy seeded 3 on lambda-300."""
    out = tmp_path_factory.mktemp("data") / "lambda-300.uavds"
    run_cli(
        "collect", "--config", CONFIG, "--set", f"world.horizon={HORIZON}",
        "--set", "collect.transitions=200", "--task", "lambda-300",
        "--policy", "random", "--seed", 3, "--out", out,
    )
    return out


def test_load_dataset_gives_what_the_python_env_and_policy_make(collected):
    data = uavmeta.load_dataset(collected)
    assert len(data) == 200 and data.task_name == "lambda-300" and data.lam == 300.0
    assert data.rain is None and data.devices == 10 and data.role == "meta-test"
    assert data.obs.shape == (200, 12) and data.obs.dtype == np.uint16
    assert data.action.dtype == np.int64 and data.reward.dtype == np.float32

    # The collector's episodes are the env's episodes of the same seed, its actions those of
    # the same random policy: the file must hold exactly what Python makes.
    env = uavmeta.UavEnv.from_config(CONFIG, task="lambda-300", horizon=HORIZON)
    policy = uavmeta.policies.random(env, seed=3)
    obs, _ = env.reset(seed=3)
    for i in range(200):
        if i and i % HORIZON == 0:
            obs, _ = env.reset()
        action = policy(obs)
        next_obs, reward, _, truncated, _ = env.step(action)
        assert data.obs[i].tolist() == obs.astype(int).tolist(), i
        assert data.action[i] == action and data.reward[i] == np.float32(reward), i
        assert data.next_obs[i].tolist() == next_obs.astype(int).tolist(), i
        assert data.truncated[i] == truncated and data.step[i] == i % HORIZON, i
        assert data.episode[i] == i // HORIZON, i
        obs = next_obs


def test_a_damaged_file_raises_naming_the_file_and_offset(collected, tmp_path):
    data = bytearray(collected.read_bytes())
    data[-10] ^= 0xFF  # inside the last chunk's payload: its CRC32 no longer matches
    bad = tmp_path / "bad.uavds"
    bad.write_bytes(bytes(data))
    with pytest.raises(uavmeta.DatasetError) as error:
        uavmeta.load_dataset(bad)
    message = str(error.value)
    assert str(bad) in message and "offset" in message, message
    assert isinstance(error.value, ValueError)

    bad.write_bytes(b"not a dataset at all")
    with pytest.raises(uavmeta.DatasetError, match="not a uavmeta dataset"):
        uavmeta.load_dataset(bad)
    with pytest.raises(FileNotFoundError, match="missing.uavds"):
        uavmeta.load_dataset(tmp_path / "missing.uavds")
