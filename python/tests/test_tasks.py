"""A task per sub-env: a list of tasks, and a sampler that draws a new task at every reset."""

import copy
import pickle

import gymnasium
import numpy as np
import pytest

import uavmeta
from conftest import CONFIG
from test_vector import same_steps

N = 6
TASKS = [100.0, dict(lam=300.0, rain=(3, 3, 5, 5)), dict(lam=700.0, rain=(1, 1, 4, 6), rain_moves_every=9)]


def single(entry, **kwargs):
    if isinstance(entry, dict):
        return uavmeta.UavEnv(**entry, **kwargs)
    return uavmeta.UavEnv(lam=entry, **kwargs)


def test_a_task_list_gives_env_i_the_task_i_mod_len_as_single_envs_do():
    ours = uavmeta.VectorEnv(N, tasks=TASKS, normalised=True)
    theirs = gymnasium.vector.SyncVectorEnv(
        [lambda e=TASKS[i % len(TASKS)]: single(e, normalised=True) for i in range(N)]
    )
    a, info = ours.reset(seed=3)
    b, their_info = theirs.reset(seed=3)
    np.testing.assert_array_equal(a, b)
    assert info["task_id"].tolist() == [i % 3 for i in range(N)]
    assert info["lam"].tolist() == [100.0, 300.0, 700.0] * 2
    np.testing.assert_array_equal(info["lam"], their_info["lam"])
    # Single envs each run their one task, id 0; the list numbers its tasks.
    assert same_steps(ours, theirs, np.random.default_rng(1), 230, N, ignore=("task_id",)) >= N
    assert ours.task_of(4) == dict(
        task_id=1, lam=300.0, rain=(3, 3, 5, 5), rain_moves_every=None,
        name="lambda-300-rain-3-3-5-5", layout_id=0, device_cells=ours.device_cells,
    )
    assert "layout_id" not in info  # one layout: no such info
    assert [t["lam"] for t in ours.tasks] == [100.0, 300.0, 700.0] * 2


def test_a_named_task_list_reads_the_config():
    env = uavmeta.VectorEnv(2, config=CONFIG, tasks=["lambda-100", "lambda-300"])
    _, info = env.reset(seed=0)
    assert info["lam"].tolist() == [100.0, 300.0]
    assert env.task_of(0)["name"] == "lambda-100"


@pytest.mark.parametrize(
    "sampler",
    [
        uavmeta.TaskSampler(TASKS),
        uavmeta.TaskSampler(lam=(0.0, 1000.0), rain_probability=0.6, rain_size=(1, 4),
                            rain_moves_every=(None, 7)),
    ],
    ids=["list", "ranges"],
)
def test_a_sampler_draws_a_task_at_every_reset_as_single_envs_draw_it(sampler):
    ours = uavmeta.VectorEnv(N, tasks=sampler, horizon=20)
    theirs = gymnasium.vector.SyncVectorEnv(
        [lambda: uavmeta.UavEnv(tasks=sampler, horizon=20) for _ in range(N)]
    )
    a, info = ours.reset(seed=11)
    b, _ = theirs.reset(seed=11)
    np.testing.assert_array_equal(a, b)
    seen = {(int(i), float(l)) for i, l in zip(info["task_id"], info["lam"])}
    rng = np.random.default_rng(2)
    for _ in range(5):  # five episodes each, the tasks redrawn at every autoreset
        same_steps(ours, theirs, rng, 21, N)
        _, _, _, _, info = ours.step(np.zeros(N, np.int64))
        theirs.step(np.zeros(N, np.int64))
        seen |= {(int(i), float(l)) for i, l in zip(info["task_id"], info["lam"])}
    assert len(seen) >= 3
    # The draws follow the seed: the same seed, the same tasks.
    again = uavmeta.VectorEnv(N, tasks=sampler, horizon=20)
    _, info2 = again.reset(seed=11)
    _, info = uavmeta.VectorEnv(N, tasks=sampler, horizon=20).reset(seed=11)
    np.testing.assert_array_equal(info["task_id"], info2["task_id"])


def test_sampled_rain_fits_the_grid_and_lambda_its_range():
    sampler = uavmeta.TaskSampler(lam=(200.0, 400.0), rain_probability=1.0, rain_size=(2, 3),
                                  rain_moves_every=5)
    env = uavmeta.VectorEnv(64, tasks=sampler, grid_cells=6)
    env.reset(seed=0)
    for task in env.tasks:
        assert 200.0 <= task["lam"] <= 400.0 and task["rain_moves_every"] == 5
        x0, y0, x1, y1 = task["rain"]
        assert 0 <= x0 <= x1 < 6 and 0 <= y0 <= y1 < 6
        assert 2 <= x1 - x0 + 1 <= 3 and 2 <= y1 - y0 + 1 <= 3


DIAGONAL = [(i, i) for i in range(10)]
LAYOUTS = [dict(lam=300.0), dict(lam=300.0, layout=7), dict(lam=800.0, layout=DIAGONAL)]


def test_a_task_with_a_layout_of_its_own_steps_as_a_world_of_that_layout():
    ours = uavmeta.VectorEnv(N, tasks=LAYOUTS)
    worlds = [dict(), dict(layout_seed=7), dict(device_cells=[list(c) for c in DIAGONAL])]
    theirs = gymnasium.vector.SyncVectorEnv(
        [lambda j=i % 3: uavmeta.UavEnv(lam=LAYOUTS[j]["lam"], **worlds[j]) for i in range(N)]
    )
    a, info = ours.reset(seed=5)
    b, _ = theirs.reset(seed=5)
    np.testing.assert_array_equal(a, b)
    assert info["layout_id"].tolist() == [0, 1, 2] * 2
    ignore = ("task_id", "layout_id", "_layout_id")  # the single envs have one task, one layout
    assert same_steps(ours, theirs, np.random.default_rng(4), 230, N, ignore=ignore) >= N
    cells = [ours.task_of(i)["device_cells"] for i in range(3)]
    assert cells[0] == ours.device_cells and cells[2] == DIAGONAL
    assert cells[1] == uavmeta.UavEnv(layout_seed=7).device_cells != cells[0]


def test_a_sampler_draws_layouts_and_a_task_of_a_layout_scores_as_its_world():
    sampler = uavmeta.TaskSampler(lam=(100.0, 900.0), layouts=(None, 7, DIAGONAL))
    env = uavmeta.VectorEnv(16, tasks=sampler, horizon=10)
    _, info = env.reset(seed=2)
    seen = set(info["layout_id"].tolist())
    for _ in range(4):  # the layout is redrawn at every autoreset, with the rest of the task
        for _ in range(11):
            _, _, _, _, info = env.step(np.zeros(16, np.int64))
        seen |= set(info["layout_id"].tolist())
    assert seen == {0, 1, 2}
    cells = [uavmeta.UavEnv().device_cells, uavmeta.UavEnv(layout_seed=7).device_cells, DIAGONAL]
    for i in range(16):
        task = env.task_of(i)
        assert info["layout_id"][i] == task["layout_id"]
        assert task["device_cells"] == cells[task["layout_id"]]
    # A task dict with its layout is scored on that layout's world, as the CLI scores it.
    task = dict(lam=300.0, layout=7)
    want = uavmeta.evaluate("greedy", uavmeta.UavEnv(lam=300.0, layout_seed=7), exact=True)
    assert uavmeta.evaluate("greedy", task, exact=True).ret.mean == want.ret.mean
    listed = uavmeta.VectorEnv(2, tasks=[300.0, task])
    assert uavmeta.evaluate("greedy", listed.tasks[1], exact=True).ret.mean == want.ret.mean


@pytest.mark.parametrize(
    "kwargs, error, needle",
    [
        (dict(tasks=[]), ValueError, "tasks = []"),
        (dict(tasks=[dict(lam=-1.0)]), ValueError, "tasks[0]: lam = -1.0"),
        (dict(tasks=[100.0, dict(lam=1.0, rain=(8, 8, 12, 12))]), ValueError, "tasks[1]"),
        (dict(tasks=[100.0, "no-such-task"]), ValueError, "no-such-task"),
        (dict(tasks=[dict(lamda=3.0)]), ValueError, "tasks[0] has ['lamda']"),
        (dict(tasks=[None]), TypeError, "tasks[0] = None"),
        (dict(tasks="lambda-300"), TypeError, "tasks = 'lambda-300'"),
        (dict(tasks=uavmeta.TaskSampler(lam=(5.0, 1.0))), ValueError, "lam = (5.0, 1.0)"),
        (dict(tasks=uavmeta.TaskSampler(lam=(1.0, 5.0), rain_size=(2, 11))), ValueError,
         "rain_size = (2, 11)"),
        (dict(tasks=uavmeta.TaskSampler(lam=(1.0, 5.0), rain_probability=2.0)), ValueError,
         "rain_probability = 2.0"),
        (dict(tasks=[dict(lam=1.0, layout="near")]), TypeError, "tasks[0]['layout'] = 'near'"),
        (dict(tasks=[dict(lam=1.0, layout=-3)]), ValueError, "tasks[0]['layout'] = -3"),
        (dict(tasks=[dict(lam=1.0, layout=[(0, 0)])]), ValueError,
         "tasks[0]['layout'] = [(0, 0)]: the default config: key `world.device_cells`"),
        (dict(tasks=[1.0, dict(lam=1.0, layout=[(0, 0)] * 10)]), ValueError,
         "a cell no other device occupies"),
        (dict(tasks=[dict(lam=1.0, layout=[(0, 10)] + DIAGONAL[1:])]), ValueError,
         "key `world.device_cells[0]` = [0, 10]: expected a cell inside the grid"),
        (dict(tasks=[dict(lam=1.0, layout=7, device_cells=DIAGONAL)]), ValueError,
         "layout and device_cells"),
        (dict(tasks=uavmeta.TaskSampler(lam=(1.0, 5.0), layouts=())), ValueError, "layouts = []"),
    ],
)
def test_bad_task_lists_and_samplers_name_the_argument(kwargs, error, needle):
    with pytest.raises(error) as e:
        uavmeta.VectorEnv(3, **kwargs)
    assert needle in str(e.value), str(e.value)


def test_bad_sampler_arguments_name_the_argument():
    with pytest.raises(ValueError, match="either a list of tasks or lam"):
        uavmeta.TaskSampler()
    with pytest.raises(TypeError, match="lam = 'wide'"):
        uavmeta.TaskSampler(lam="wide")
    with pytest.raises(ValueError, match=r"rain_moves_every\[1\] = -2"):
        uavmeta.TaskSampler(lam=(0, 1), rain_moves_every=[None, -2])
    with pytest.raises(TypeError, match="a list of tasks, one per sub-env, is for VectorEnv"):
        uavmeta.UavEnv(tasks=[100.0, 300.0])
    with pytest.raises(TypeError, match=r"layouts\[1\]\[0\] = \(1, 2, 3\): expected an \(x, y\)"):
        uavmeta.TaskSampler(lam=(0, 1), layouts=(None, [(1, 2, 3)]))
    with pytest.raises(TypeError, match="layouts = 7: expected a list of layouts"):
        uavmeta.TaskSampler(lam=(0, 1), layouts=7)


@pytest.mark.parametrize("tasks", [None, uavmeta.TaskSampler(lam=(0.0, 900.0), rain_probability=0.5,
                                                             rain_moves_every=(None, 4))])
def test_a_uav_env_pickles_and_deep_copies_with_its_state(tasks):
    env = uavmeta.UavEnv(lam=None if tasks else 300.0, rain=None if tasks else (2, 2, 4, 4),
                         rain_moves_every=None if tasks else 3, normalised=True, tasks=tasks)
    fresh = pickle.loads(pickle.dumps(env))  # never reset: still refuses to step
    with pytest.raises(uavmeta.ResetNeeded):
        fresh.step(0)
    env.reset(seed=4)
    env.reset()
    for a in range(13):
        env.step(a)
    clones = [pickle.loads(pickle.dumps(env)), copy.deepcopy(env)]
    for clone in clones:
        assert clone.t == env.t and clone.uav == env.uav and clone.rain_zone == env.rain_zone
        assert clone.task_of() == env.task_of()
    for a in np.random.default_rng(0).integers(0, 50, 150):
        want = env.step(int(a))
        for clone in clones:
            for w, g in zip(want, clone.step(int(a))):
                np.testing.assert_array_equal(w, g)
        if want[3]:
            break
    # Both go on to the same next episode, task and all.
    want = env.reset()
    for clone in clones:
        got = clone.reset()
        np.testing.assert_array_equal(want[0], got[0])
        assert want[1] == got[1]
    wrapped = gymnasium.make(uavmeta.ENV_ID, lam=300.0)
    wrapped.reset(seed=1)
    assert pickle.loads(pickle.dumps(wrapped)).unwrapped.uav == wrapped.unwrapped.uav


def test_a_config_task_with_a_layout_of_its_own_flies_that_layout(tmp_path):
    path = tmp_path / "layouts.toml"
    diagonal = ", ".join(f"[{x}, {y}]" for x, y in DIAGONAL)
    path.write_text(
        '[[tasks]]\nname = "plain"\nlambda = 300.0\nrole = "meta-train"\n\n'
        '[[tasks]]\nname = "seeded"\nlambda = 300.0\nrole = "meta-train"\nlayout_seed = 7\n\n'
        f'[[tasks]]\nname = "placed"\nlambda = 800.0\nrole = "meta-test"\ndevice_cells = [{diagonal}]\n'
    )
    ours = uavmeta.VectorEnv(3, config=str(path), tasks=["plain", "seeded", "placed"])
    want = [uavmeta.UavEnv().device_cells, uavmeta.UavEnv(layout_seed=7).device_cells, DIAGONAL]
    assert [ours.task_of(i)["device_cells"] for i in range(3)] == want
    for name, cells in zip(["plain", "seeded", "placed"], want):
        assert uavmeta.UavEnv(config=str(path), task=name).device_cells == cells
    # Each steps as the world of its layout.
    worlds = [dict(), dict(layout_seed=7), dict(device_cells=[list(c) for c in DIAGONAL])]
    lams = [300.0, 300.0, 800.0]
    theirs = gymnasium.vector.SyncVectorEnv(
        [lambda j=j: uavmeta.UavEnv(lam=lams[j], **worlds[j]) for j in range(3)]
    )
    a, _ = ours.reset(seed=5)
    b, _ = theirs.reset(seed=5)
    np.testing.assert_array_equal(a, b)
    ignore = ("task_id", "layout_id", "_layout_id")
    assert same_steps(ours, theirs, np.random.default_rng(4), 230, 3, ignore=ignore) >= 3
