"""The uavmeta world from Python, in the order a newcomer meets it: one env, a heuristic, the
batched vector env, a picture, (with --dataset FILE) a collected dataset and (with --checkpoint
PATH) a Q-network the command line trained.

    pip install ./python          # or: make python (into the test virtualenv); --png needs the
                                  # png extra: pip install "uavmeta[png]"
    python examples/python_quickstart.py [--dataset data/lambda-300.uavds] [--png world.png] \
        [--checkpoint runs/default/seed-0/inits/w0]
"""

import argparse

import gymnasium
import numpy as np

import uavmeta


def one_env():
    # The paper's unseen task, lambda = 300, with a rain zone over cells (3..5, 3..5).
    env = gymnasium.make("uavmeta/UAV-v0", lam=300.0, rain=(3, 3, 5, 5))
    obs, info = env.reset(seed=0)  # the episode `uavmeta env rollout --seed 0` runs first
    print("observation [x, y, A_1..A_K]:", obs.astype(int).tolist())
    episode(env, "stalest", uavmeta.policies.stalest(env))  # serve the stalest, fly towards it
    return env


def episode(env, name, policy, seed=0):
    obs, info = env.reset(seed=seed)
    ret, outages, truncated = 0.0, 0, False
    while not truncated:
        obs, reward, terminated, truncated, info = env.step(policy(obs))
        ret += reward
        outages += info["outage"]
    print(f"{name}: return {ret:.1f}, last step AoI {info['aoi']:.2f}, "
          f"{info['power_mw']:.3f} mW, {outages} outages")


def vector_env():
    # 4096 worlds stepped in one Rust call; next-step autoreset as Gymnasium 1.x defines it.
    envs = uavmeta.VectorEnv(4096, lam=300.0, normalised=True)
    obs, _ = envs.reset(seed=0)
    total = np.zeros(envs.num_envs)
    for _ in range(envs.horizon):
        obs, reward, terminated, truncated, info = envs.step(envs.action_space.sample())
        total += reward
    print(f"random policy over {envs.num_envs} episodes: mean return {total.mean():.1f}")


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--dataset", help="a .uavds file from `uavmeta collect`")
    parser.add_argument("--png", help="save the last frame here (needs Pillow)")
    parser.add_argument("--checkpoint", help="a Q-network `uavmeta` saved, without extension")
    args = parser.parse_args()
    env = one_env()
    vector_env()
    frame = env.unwrapped.render_trajectory()
    print("frame:", frame.shape, frame.dtype)
    if args.png:
        try:
            from PIL import Image
        except ImportError:
            parser.exit(2, "--png needs Pillow: pip install 'uavmeta[png]' (or pillow)\n")

        Image.fromarray(frame).save(args.png)
        print("wrote", args.png)
    if args.checkpoint:
        # The config the network was trained with, so that its world is the env's.
        env = uavmeta.UavEnv.from_config(f"{args.checkpoint}.toml", lam=300.0)
        episode(env, args.checkpoint, uavmeta.policies.checkpoint(env, args.checkpoint))
    if args.dataset:
        data = uavmeta.load_dataset(args.dataset)
        print(f"{args.dataset}: {len(data)} transitions of task {data.task_name} "
              f"(lambda = {data.lam}), obs {data.obs.shape}, mean reward {data.reward.mean():.2f}")


if __name__ == "__main__":
    main()
