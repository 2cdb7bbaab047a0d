"""uavmeta.sb3.SB3VecEnv: the fast vector env under Stable-Baselines3, against SB3's own
DummyVecEnv of UavEnvs, and SB3's PPO and DQN learning on it for a few thousand steps."""

import os

import numpy as np
import pytest

import uavmeta

if os.environ.get("CI") == "true":
    import stable_baselines3 as sb3
else:
    sb3 = pytest.importorskip("stable_baselines3")
from stable_baselines3.common.logger import configure  # noqa: E402
from stable_baselines3.common.vec_env import DummyVecEnv, VecMonitor  # noqa: E402

import uavmeta.sb3  # noqa: E402

N = 4
KW = dict(lam=300.0, rain=(2, 2, 5, 5), horizon=25, normalised=True)


def test_the_adapter_steps_as_sb3s_dummy_vec_env_of_uav_envs():
    ours = uavmeta.sb3.SB3VecEnv(uavmeta.VectorEnv(N, **KW))
    theirs = DummyVecEnv([lambda: uavmeta.UavEnv(**KW) for _ in range(N)])
    ours.seed(5)
    theirs.seed(5)
    np.testing.assert_array_equal(ours.reset(), theirs.reset())
    assert ours.reset_infos == theirs.reset_infos
    rng = np.random.default_rng(0)
    dones = 0
    for t in range(80):
        actions = rng.integers(0, 50, N)
        ours.step_async(actions)
        theirs.step_async(actions)
        (o, r, d, i), (o2, r2, d2, i2) = ours.step_wait(), theirs.step_wait()
        np.testing.assert_array_equal(o, o2, err_msg=str(t))
        np.testing.assert_array_equal(r, r2)
        np.testing.assert_array_equal(d, d2)
        for mine, want in zip(i, i2):
            assert mine.keys() == want.keys(), t
            for key in mine:
                np.testing.assert_array_equal(mine[key], want[key], err_msg=f"{key} at {t}")
        dones += int(d.sum())
    assert dones == 3 * N  # three episodes of 25 steps each


@pytest.mark.parametrize("algo", ["PPO", "DQN"])
def test_ppo_and_dqn_learn_on_the_adapter(algo, tmp_path):
    venv = VecMonitor(uavmeta.sb3.SB3VecEnv(uavmeta.VectorEnv(8, **KW)))
    kwargs = dict(n_steps=64, batch_size=128) if algo == "PPO" else dict(
        learning_starts=256, buffer_size=5000, train_freq=4, target_update_interval=250)
    model = getattr(sb3, algo)("MlpPolicy", venv, seed=0, device="cpu", **kwargs)
    # SB3's default logger makes a folder under /tmp that nobody removes; pytest removes tmp_path.
    model.set_logger(configure(str(tmp_path), []))
    model.learn(total_timesteps=4096)
    assert model.num_timesteps >= 4096
    episodes = list(model.ep_info_buffer)
    assert len(episodes) >= 100 and all(e["l"] == 25 for e in episodes)
    # The trained model scores through uavmeta.evaluate like any policy.
    score = uavmeta.evaluate(model, uavmeta.UavEnv(**KW), exact=False, episodes=8, seed=1,
                             trapped=False)
    assert score.num_episodes == 8 and np.isfinite(score.ret.mean)


def test_the_adapter_takes_only_a_uavmeta_vector_env():
    with pytest.raises(TypeError, match="expected a uavmeta.VectorEnv"):
        uavmeta.sb3.SB3VecEnv(uavmeta.UavEnv(lam=300.0))
