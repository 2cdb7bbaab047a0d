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


def test_a_normalised_dataset_matches_the_normalised_env_bit_for_bit(collected):
    raw = uavmeta.load_dataset(collected)
    data = uavmeta.load_dataset(collected, normalised=True)
    assert data.normalised and data.obs.dtype == np.float32 and data.obs.shape == (200, 12)
    assert data.observation_scale == (9.0, 9.0) + (100.0,) * 10
    assert (data.grid_cells, data.horizon, data.aoi_max) == (10, HORIZON, 100)
    # Time-limit episodes: no terminal state, a truncation at every horizon.
    assert data.terminals.dtype == bool and not data.terminals.any()
    np.testing.assert_array_equal(data.truncations, raw.truncated)
    assert data.truncations.sum() == 200 // HORIZON
    assert data.task_params == dict(name="lambda-300", task_id=data.task_id, lam=300.0,
                                    rain=None, rain_moves_every=None, role="meta-test")
    env = uavmeta.UavEnv.from_config(CONFIG, task="lambda-300", horizon=HORIZON, normalised=True)
    obs, _ = env.reset(seed=3)
    policy = uavmeta.policies.random(env, seed=3)
    for i in range(2 * HORIZON):
        if i and i % HORIZON == 0:
            obs, _ = env.reset()
        assert data.obs[i].tobytes() == obs.tobytes(), i  # bit for bit
        obs, *_ = env.step(policy(obs))
        assert data.next_obs[i].tobytes() == obs.tobytes(), i


def test_bad_dataset_arguments_raise_the_right_error(collected, tmp_path):
    with pytest.raises(TypeError, match="path = None"):
        uavmeta.load_dataset(None)
    with pytest.raises(TypeError, match="path = 3"):
        uavmeta.load_dataset(3)
    with pytest.raises(TypeError, match="normalised = 'yes'"):
        uavmeta.load_dataset(collected, normalised="yes")
    with pytest.raises(FileNotFoundError, match="config = .*nowhere.toml"):
        uavmeta.load_dataset(collected, config=tmp_path / "nowhere.toml")
    lone = tmp_path / "lone.uavds"
    lone.write_bytes(collected.read_bytes())
    assert uavmeta.load_dataset(lone).lam is None  # no config: no task parameters
    with pytest.raises(ValueError, match="normalised = True.*expected config="):
        uavmeta.load_dataset(lone, normalised=True)


def test_the_minari_export_carries_the_same_observations_columns_and_task(collected, run_cli,
                                                                           tmp_path, monkeypatch):
    minari = pytest.importorskip("minari")
    run_cli("dataset", "export", "--dataset", collected, "--format", "minari", "--normalised",
            "--out", tmp_path)
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path))
    exported = minari.load_dataset("uavmeta/lambda-300-v0")
    data = uavmeta.load_dataset(collected, normalised=True)
    meta = exported.storage.metadata
    assert meta["normalised"] is True and meta["lambda"] == 300.0 and meta["task"] == "lambda-300"
    assert meta["task_id"] == data.task_id and meta["role"] == "meta-test"
    assert tuple(meta["observation_scale"]) == data.observation_scale
    assert exported.observation_space.high.max() == 1.0
    row = 0
    for episode in exported.iterate_episodes():
        n = len(episode.actions)
        assert episode.observations[:-1].tobytes() == data.obs[row:row + n].tobytes()
        assert episode.observations[-1].tobytes() == data.next_obs[row + n - 1].tobytes()
        assert not episode.terminations.any()
        np.testing.assert_array_equal(episode.truncations, data.truncations[row:row + n])
        row += n
    assert row == len(data)
