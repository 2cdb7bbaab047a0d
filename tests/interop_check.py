"""Loads `uavmeta dataset export`'s output with the consumers themselves and checks it against the
source transitions; run by tests/interop.rs as `python interop_check.py DIR`.

DIR holds expected.json (the source's transitions, all and N shots, and its task), the exports
full.npz and shots.npz, and a Minari datasets root `minari/` with both datasets. Every check is an
assert; the last line printed sums up what was checked.
"""

import json
import os
import sys

import numpy as np

DIR = sys.argv[1]
os.environ["MINARI_DATASETS_PATH"] = os.path.join(DIR, "minari")

import d3rlpy  # noqa: E402
import minari  # noqa: E402

with open(os.path.join(DIR, "expected.json")) as f:
    EXPECTED = json.load(f)
ACTIONS = EXPECTED["action_count"]


def in_step_order(transitions):
    """Source transitions as (obs, action, reward, next_obs) in the exports' order."""
    ordered = sorted(transitions, key=lambda t: (t["actor"], t["episode"], t["step"]))
    return [(t["obs"], t["action"], t["reward"], t["next_obs"]) for t in ordered]


def assert_same(got, expected, what):
    assert len(got) == len(expected), f"{what}: {len(got)} transitions, expected {len(expected)}"
    for i, (g, e) in enumerate(zip(got, expected)):
        assert list(g[0]) == e[0] and g[1] == e[1] and list(g[3]) == e[3], f"{what} {i}: {g} != {e}"
        assert np.float32(g[2]) == np.float32(e[2]), f"{what} {i}: reward {g[2]} != {e[2]}"


def check_npz(name, transitions):
    """The flat arrays, then the transitions d3rlpy's MDPDataset makes of them."""
    data = np.load(os.path.join(DIR, name))
    assert sorted(data.files) == sorted(
        ["observations", "actions", "rewards", "terminals", "timeouts", "next_observations"]
    ), data.files
    obs, timeouts = data["observations"], data["timeouts"]
    rows, width = obs.shape
    assert obs.dtype == np.float32 and data["actions"].dtype == np.int64
    assert data["next_observations"].shape == (rows, width) and width == EXPECTED["observation_len"]
    assert not data["terminals"].any()
    runs = int(timeouts.sum())
    assert rows == len(transitions) + runs, (rows, len(transitions), runs)
    real = timeouts == 0
    flat = list(zip(obs[real].astype(int).tolist(), data["actions"][real].tolist(),
                    data["rewards"][real].tolist(), data["next_observations"][real].astype(int).tolist()))
    assert_same(flat, in_step_order(transitions), f"{name} rows")

    dataset = d3rlpy.dataset.MDPDataset(
        data["observations"], data["actions"], data["rewards"], data["terminals"], data["timeouts"],
        action_size=ACTIONS,
    )
    assert dataset.transition_count == len(transitions), dataset.transition_count
    picker = d3rlpy.dataset.BasicTransitionPicker()
    picked = [picker(episode, i) for episode in dataset.episodes for i in range(episode.transition_count)]
    picked = [(p.observation.astype(int).tolist(), int(p.action[0]), float(p.reward[0]),
               p.next_observation.astype(int).tolist()) for p in picked]
    assert_same(picked, in_step_order(transitions), f"{name} in d3rlpy")
    return dataset, runs


def train_discrete_cql(dataset, steps=20):
    """A few DiscreteCQL gradient steps: finite losses, greedy actions in range."""
    d3rlpy.seed(0)
    cql = d3rlpy.algos.DiscreteCQLConfig(batch_size=32).create(device="cpu:0")
    history = cql.fit(
        dataset, n_steps=steps, n_steps_per_epoch=steps, show_progress=False,
        logger_adapter=d3rlpy.logging.NoopAdapterFactory(),
    )
    loss = history[-1][1]["loss"]
    assert np.isfinite(loss), history
    greedy = cql.predict(dataset.episodes[0].observations)
    assert ((0 <= greedy) & (greedy < ACTIONS)).all(), greedy
    return loss


def check_minari(dataset_id, transitions):
    """The dataset Minari loads: episodes, flags, spaces and uavmeta's metadata."""
    assert dataset_id in minari.list_local_datasets(), minari.list_local_datasets()
    ds = minari.load_dataset(dataset_id)
    assert ds.total_steps == len(transitions), ds.total_steps
    assert ds.observation_space.shape == (EXPECTED["observation_len"],)
    assert ds.action_space.n == ACTIONS
    steps, truncated = [], []
    for episode in ds.iterate_episodes():
        n = len(episode)
        assert episode.observations.shape == (n + 1, EXPECTED["observation_len"])
        assert episode.actions.shape == (n,) and not episode.terminations.any()
        truncated += episode.truncations.tolist()
        steps += [(episode.observations[i].astype(int).tolist(), int(episode.actions[i]),
                   float(episode.rewards[i]), episode.observations[i + 1].astype(int).tolist())
                  for i in range(n)]
    assert_same(steps, in_step_order(transitions), f"minari {dataset_id}")
    ordered = sorted(transitions, key=lambda t: (t["actor"], t["episode"], t["step"]))
    assert truncated == [t["truncated"] for t in ordered], "truncations"
    metadata = ds.storage.metadata
    for key in ["task", "lambda", "rain"]:
        assert metadata[key] == EXPECTED[key], (key, metadata[key], EXPECTED[key])
    assert f'name = "{EXPECTED["task"]}"' in metadata["config"], metadata["config"]
    return ds.total_episodes, sum(truncated)


full, full_runs = check_npz("full.npz", EXPECTED["full"])
shots, shot_runs = check_npz("shots.npz", EXPECTED["shots"])
loss = train_discrete_cql(full)
episodes, truncations = check_minari(EXPECTED["minari_full"], EXPECTED["full"])
shot_episodes, _ = check_minari(EXPECTED["minari_shots"], EXPECTED["shots"])
assert (episodes, shot_episodes) == (full_runs, shot_runs)
print(
    f"numpy {np.__version__}, d3rlpy {d3rlpy.__version__}, minari {minari.__version__}: "
    f"full.npz {len(EXPECTED['full'])} transitions in {full_runs} runs, "
    f"shots.npz {len(EXPECTED['shots'])} in {shot_runs}, every one as in the source; "
    f"Minari {episodes} + {shot_episodes} episodes, {truncations} truncations; "
    f"DiscreteCQL 20 steps, loss {loss:.3f}"
)
