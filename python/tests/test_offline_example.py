"""examples/offline_cql.py, the single-file offline learner, on a small budget: it trains on a
dataset `uavmeta collect` wrote, scores itself with uavmeta.evaluate, and saves a checkpoint whose
`uavmeta eval` return is the one it printed."""

import re
import subprocess
import sys

import pytest

from conftest import CONFIG, REPO

pytest.importorskip("torch")


def test_the_offline_cql_example_trains_scores_and_saves(run_cli, tmp_path):
    data = tmp_path / "lambda-300.uavds"
    # The planner's tests' 4 x 4 world: its exact reference (100 start cells on the default
    # world, over a minute) takes a second here.
    small = [f"--set={s}" for s in ("world.grid_cells=4", "world.devices=3", "world.horizon=20",
                                    "world.cell_m=200", "world.layout_seed=3")]
    run_cli("collect", "--config", CONFIG, *small, "--task", "lambda-300", "--policy", "eps:0.3",
            "--transitions", 2000, "--seed", 1, "--out", data)
    out = subprocess.run(
        [sys.executable, str(REPO / "examples" / "offline_cql.py"), "--dataset", str(data),
         "--total-steps", "300", "--log-every", "100", "--save", str(tmp_path / "cql")],
        capture_output=True, text=True, cwd=tmp_path,
    )
    assert out.returncode == 0, out.stderr
    assert len(re.findall(r"^step=\d+ losses/td_loss=\S+ losses/cql_loss=\S+", out.stdout, re.M)) == 3
    ret = re.search(r"eval/return=(-?[\d.]+) eval/return_ci95=([\d.]+)", out.stdout).groups()
    score = float(re.search(r"eval/normalised_score=(-?[\d.]+)", out.stdout).group(1))
    assert -100 < score < 150, out.stdout
    cli = run_cli("eval", "--config", f"{data}.config.toml", "--task", "lambda-300",
                  "--checkpoint", tmp_path / "cql").stdout
    assert f"  return    {ret[0]} ± {ret[1]}\n" in cli, (cli, out.stdout)
