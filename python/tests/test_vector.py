"""VectorEnv against N single envs in Gymnasium's own SyncVectorEnv."""

import gymnasium
import numpy as np
import pytest

import uavmeta

N = 5


def sync_env(**kwargs):
    return gymnasium.vector.SyncVectorEnv(
        [lambda: uavmeta.UavEnv(**kwargs) for _ in range(N)]
    )


@pytest.mark.parametrize(
    "kwargs",
    [dict(lam=300.0), dict(lam=700.0, rain=(1, 1, 4, 6), rain_moves_every=9, normalised=True, horizon=37)],
)
def test_the_vector_env_equals_n_single_envs(kwargs):
    ours, theirs = uavmeta.VectorEnv(N, **kwargs), sync_env(**kwargs)
    assert ours.single_observation_space == theirs.single_observation_space
    assert ours.observation_space == theirs.observation_space
    assert ours.action_space == theirs.action_space
    a, _ = ours.reset(seed=11)
    b, _ = theirs.reset(seed=11)
    np.testing.assert_array_equal(a, b)
    rng = np.random.default_rng(0)
    autoresets = same_steps(ours, theirs, rng, 260)
    assert autoresets >= 2 * N  # the run crossed autoresets
    # A reset without a seed: every env goes on to its next episode, in both.
    a, _ = ours.reset()
    b, _ = theirs.reset()
    np.testing.assert_array_equal(a, b)
    same_steps(ours, theirs, rng, 40)


def same_steps(ours, theirs, rng, steps, n=N, ignore=()):
    """Steps both with the same random actions, checking every array (but the info keys
    ``ignore``); returns how many env steps were autoresets."""
    autoresets = 0
    for t in range(steps):
        actions = rng.integers(0, ours.single_action_space.n, size=n)
        got, want = ours.step(actions), theirs.step(actions)
        for g, w in zip(got[:4], want[:4]):
            assert g.dtype == w.dtype and g.shape == w.shape
            np.testing.assert_array_equal(g, w, err_msg=f"step {t}")
        assert set(got[4]) - set(ignore) == set(want[4]) - set(ignore), t
        for key in set(got[4]) - set(ignore):
            assert got[4][key].dtype == want[4][key].dtype, key
            np.testing.assert_array_equal(got[4][key], want[4][key], err_msg=f"{key} at {t}")
        autoresets += int((~got[4].get("_aoi", np.zeros(n, bool))).sum())
    return autoresets


def test_reset_takes_a_list_of_seeds_and_make_vec_finds_the_vector_env():
    env = gymnasium.make_vec("uavmeta/UAV-v0", num_envs=3, vectorization_mode="vector_entry_point", lam=300.0)
    assert isinstance(env, uavmeta.VectorEnv) and env.num_envs == 3
    a, _ = env.reset(seed=[4, 5, 6])
    b, _ = env.reset(seed=4)
    np.testing.assert_array_equal(a, b)
    single = uavmeta.UavEnv(lam=300.0)
    np.testing.assert_array_equal(a[2], single.reset(seed=6)[0])


@pytest.mark.parametrize(
    "actions, needle",
    [
        (np.array([0, 1, 50]), "actions[2] = 50"),
        (np.array([0, -3, 1]), "actions[1] = -3"),
        (np.array([0, 1]), "shape (2,)"),
        (np.array([0, 2**63, 1], dtype=np.uint64), "actions[1] = 9223372036854775808"),
    ],
)
def test_bad_actions_raise_value_errors_naming_them(actions, needle):
    env = uavmeta.VectorEnv(3, lam=300.0)
    env.reset(seed=0)
    with pytest.raises(ValueError) as error:
        env.step(actions)
    assert needle in str(error.value), str(error.value)
    env.step(np.array([0, 1, 2]))  # the env is still usable


@pytest.mark.parametrize("num_envs", [0, 1 << 30, -2])
def test_a_bad_num_envs_raises_a_value_error(num_envs):
    with pytest.raises(ValueError, match=f"num_envs = {num_envs}"):
        uavmeta.VectorEnv(num_envs, lam=300.0)


def test_float_actions_are_a_type_error_and_step_before_reset_is_refused():
    env = uavmeta.VectorEnv(3, lam=300.0)
    with pytest.raises(uavmeta.ResetNeeded, match="reset"):
        env.step(np.array([0, 1, 2]))
    assert isinstance(uavmeta.ResetNeeded("x"), (RuntimeError, gymnasium.error.ResetNeeded))
    env.reset(seed=0)
    with pytest.raises(TypeError, match="dtype float64"):
        env.step(np.array([0.0, 1.0, 2.0]))
