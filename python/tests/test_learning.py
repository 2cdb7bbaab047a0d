"""A real consumer learns in the env: Stable-Baselines3's DQN, a bounded number of steps."""

import os

import gymnasium
import pytest

import uavmeta

if os.environ.get("CI") == "true":  # required there, as every interop package
    import stable_baselines3 as sb3
else:
    sb3 = pytest.importorskip("stable_baselines3")
import torch  # noqa: E402  (stable-baselines3 depends on it)

LAM = 300.0
EVAL_SEED = 1000
EPISODES = 10


def mean_return(env, act):
    total = 0.0
    obs, _ = env.reset(seed=EVAL_SEED)
    for e in range(EPISODES):
        if e:
            obs, _ = env.reset()
        truncated = False
        while not truncated:
            obs, reward, _, truncated, _ = env.step(act(obs))
            total += reward
    return total / EPISODES


def test_sb3_dqn_beats_the_random_policy(tmp_path):
    torch.manual_seed(0)
    torch.set_num_threads(1)

    # Rewards / 100 (the paper's figures' scale) keep the TD targets near 1.
    train = gymnasium.wrappers.TransformReward(
        uavmeta.UavEnv(lam=LAM, normalised=True), lambda r: r / 100.0
    )
    model = sb3.DQN(
        "MlpPolicy", train, seed=0, learning_starts=1_000, buffer_size=20_000,
        train_freq=4, target_update_interval=500, exploration_fraction=0.3,
        exploration_final_eps=0.02, learning_rate=1e-3, gamma=0.95,
        policy_kwargs=dict(net_arch=[128, 128]), device="cpu",
    )
    # SB3's default logger makes a folder under /tmp that nobody removes; pytest removes tmp_path.
    from stable_baselines3.common.logger import configure

    model.set_logger(configure(str(tmp_path), []))
    model.learn(total_timesteps=20_000)

    env = uavmeta.UavEnv(lam=LAM, normalised=True)
    dqn = mean_return(env, lambda obs: int(model.predict(obs, deterministic=True)[0]))
    random = uavmeta.policies.random(env, seed=5)
    baseline = mean_return(env, random)
    print(f"DQN {dqn:.0f}, random {baseline:.0f} (mean return of {EPISODES} episodes)")
    # Returns are negative: at least a quarter better than random.
    assert dqn > baseline * 0.75, (dqn, baseline)

