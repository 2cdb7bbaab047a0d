"""uavmeta.evaluate, references and normalised_score against the command line: the same figures
to the digit as `uavmeta env rollout --exact --json` and `uavmeta eval --per-episode`."""

import json
import re

import numpy as np
import pytest

import uavmeta
from conftest import CONFIG

# A small world, so that the planner's exact evaluation takes a second, not a minute.
SMALL = ("world.horizon=20", "world.grid_cells=6", "world.devices=4")
SMALL_KW = dict(horizon=20, grid_cells=6, devices=4)
TASKS = {
    "rain": (["--lambda", "300", "--rain", "1,1,3,3"], dict(lam=300.0, rain=(1, 1, 3, 3))),
    "moving": (
        ["--lambda", "500", "--rain", "0,2,2,4", "--rain-moves-every", "6"],
        dict(lam=500.0, rain=(0, 2, 2, 4), rain_moves_every=6),
    ),
}


def rollout_json(run_cli, policy, task_args, seed, episodes=12, exact=True):
    args = ["env", "rollout", "--config", CONFIG, *task_args, "--policy", policy,
            "--episodes", episodes, "--seed", seed, "--json"]
    for s in SMALL:
        args += ["--set", s]
    return json.loads(run_cli(*args, *(["--exact"] if exact else [])).stdout)


def cli_line(name, estimate, digits):
    """A summary line of `uavmeta eval`: the mean and its 95% half-width."""
    return f"  {name:<9} {estimate.mean:.{digits}f} ± {estimate.ci95:.{digits}f}\n"


def assert_same_as_cli(score, summary):
    """Every episode's figures and every mean and interval, exactly."""
    cli = summary["episodes"]
    assert score.num_episodes == len(cli)
    for key in ("ret", "aoi", "power_mw", "outages"):
        assert score.episodes[key].tolist() == [e[key] for e in cli], key
        mine = getattr(score, key)
        assert (mine.mean, mine.ci95) == (summary["mean"][key]["mean"], summary["mean"][key]["ci95"]), key


@pytest.mark.parametrize("task", sorted(TASKS))
@pytest.mark.parametrize("policy", ["random", "stalest", "greedy", "planner", "eps:0.2"])
@pytest.mark.parametrize("exact", [True, False])
def test_a_named_policy_scores_as_env_rollout(run_cli, task, policy, exact):
    cli_args, kwargs = TASKS[task]
    summary = rollout_json(run_cli, policy, cli_args, seed=7, exact=exact)
    score = uavmeta.evaluate(policy, kwargs, config=CONFIG, seed=7, episodes=12, exact=exact,
                             **SMALL_KW)
    assert_same_as_cli(score, summary)
    expected = 36 if exact and task == "rain" else 12  # every start cell where the rain stays
    assert score.num_episodes == expected


@pytest.mark.parametrize("task", sorted(TASKS))
def test_a_python_callable_scores_as_the_cli_runs_the_same_policy(run_cli, task):
    cli_args, kwargs = TASKS[task]
    # Stalest reads the observation alone (greedy would price rain at the task's configured
    # zone, where the CLI's reads the world's moving one).
    summary = rollout_json(run_cli, "stalest", cli_args, seed=3)
    env = uavmeta.UavEnv(config=CONFIG, normalised=True, **kwargs, **SMALL_KW)
    stalest = uavmeta.policies.stalest(env)
    seen = []

    def policy(obs):  # a plain callable: stepped in lockstep from Python
        seen.append(obs.shape)
        return stalest(obs)

    score = uavmeta.evaluate(policy, env, seed=3, episodes=12)
    assert_same_as_cli(score, summary)
    assert len(seen) == 20 and seen[0] == (score.num_episodes, 6)


def test_a_checkpoint_scores_as_uavmeta_eval_to_the_digit(run_cli, trained):
    out = run_cli("eval", "--config", CONFIG, "--task", "lambda-300", "--checkpoint", trained,
                  "--per-episode").stdout
    env = uavmeta.UavEnv.from_config(CONFIG, task="lambda-300", normalised=True)
    score = uavmeta.evaluate(uavmeta.policies.checkpoint(env, trained), env)
    assert score.num_episodes == 100 and score.exact
    assert cli_line("return", score.ret, 1) in out, out
    assert cli_line("AoI", score.aoi, 3) in out
    assert cli_line("power mW", score.power_mw, 4) in out
    assert cli_line("outages", score.outages, 2) in out
    rows = re.findall(r"^\s+\d+\s+\(\s*(\d+),\s*(\d+)\)\s+(\S+)\s+(\S+)\s+(\S+)\s+(\d+)(  trapped)?$",
                      out, re.M)
    assert len(rows) == 100
    e = score.episodes
    for i, (x, y, ret, aoi, power, outages, trapped) in enumerate(rows):
        assert (int(x), int(y)) == tuple(e["start"][i])
        assert (ret, aoi, power) == (f"{e['ret'][i]:.1f}", f"{e['aoi'][i]:.2f}", f"{e['power_mw'][i]:.4f}")
        assert int(outages) == e["outages"][i]
        assert bool(trapped) == (tuple(e["start"][i]) in score.trapped)
    count = int(re.search(r"trapped\s+(\d+) of 100", out).group(1))
    assert count == len(score.trapped)


def test_references_and_the_normalised_score(run_cli):
    cli_args, kwargs = TASKS["rain"]
    refs = uavmeta.references(kwargs, config=CONFIG, seed=7, **SMALL_KW)
    assert list(refs) == ["random", "stalest", "greedy", "planner"]
    for name, score in refs.items():
        assert_same_as_cli(score, rollout_json(run_cli, name, cli_args, seed=7))
    assert refs["planner"].ret.mean > max(s.ret.mean for s in refs.values() if s is not refs["planner"])
    norm = lambda s: uavmeta.normalised_score(s, kwargs, config=CONFIG, **SMALL_KW)
    assert norm(refs["random"]) == 0.0 and norm(refs["planner"]) == 100.0
    greedy = refs["greedy"].ret.mean
    want = 100 * (greedy - refs["random"].ret.mean) / (refs["planner"].ret.mean - refs["random"].ret.mean)
    assert norm(refs["greedy"]) == pytest.approx(want, rel=1e-12) and 0 < want < 100


def test_bad_evaluations_raise_errors_naming_the_argument():
    env = uavmeta.UavEnv(lam=300.0, **SMALL_KW)
    with pytest.raises(TypeError, match="policy = 3"):
        uavmeta.evaluate(3, env)
    with pytest.raises(ValueError, match="policy `best`: expected random, stalest"):
        uavmeta.evaluate("best", env)
    with pytest.raises(ValueError, match="episodes = 0"):
        uavmeta.evaluate("random", env, episodes=0, exact=False)
    with pytest.raises(TypeError, match="task = \\[1, 2\\]"):
        uavmeta.evaluate("random", [1, 2])
    with pytest.raises(ValueError, match="runs several tasks"):
        uavmeta.evaluate("random", uavmeta.VectorEnv(2, tasks=[1.0, 2.0]))
    with pytest.raises(ValueError, match="returned actions of shape"):
        uavmeta.evaluate(lambda obs: np.zeros(3, np.int64), env)
    with pytest.raises(TypeError, match="dtype float64"):
        uavmeta.evaluate(lambda obs: np.zeros(len(obs)), env)
    with pytest.raises(ValueError, match="for episode 0 = 50"):
        uavmeta.evaluate(lambda obs: np.full(len(obs), 50), env)
    with pytest.raises(TypeError, match="score = 'high'"):
        uavmeta.normalised_score("high", env)
