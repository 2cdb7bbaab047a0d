"""Shared fixtures: the repository, the ``uavmeta`` binary the CLI comparisons run, and its
default config. tests/python.rs runs this suite with UAVMETA_BIN set to the binary cargo built."""

import os
import pathlib
import subprocess

import pytest

REPO = pathlib.Path(__file__).resolve().parents[2]
CONFIG = REPO / "configs" / "default.toml"


@pytest.fixture(scope="session")
def uavmeta_bin():
    """The CLI (UAVMETA_BIN, else target/release/uavmeta); the tests that compare with it skip
    without it, except under CI=true."""
    path = os.environ.get("UAVMETA_BIN") or str(REPO / "target" / "release" / "uavmeta")
    if not os.path.exists(path):
        if os.environ.get("CI") == "true":
            pytest.fail(f"required under CI=true: the uavmeta binary {path}")
        pytest.skip(f"no uavmeta binary at {path} (set UAVMETA_BIN)")
    return path


@pytest.fixture(scope="session")
def run_cli(uavmeta_bin):
    def run(*args, cwd=None):
        out = subprocess.run(
            [uavmeta_bin, *map(str, args)], capture_output=True, text=True, cwd=cwd
        )
        assert out.returncode == 0, out.stderr
        return out

    return run


@pytest.fixture(scope="session")
def trained(run_cli, tmp_path_factory):
    """A CQL network trained for 60 epochs on 400 shots of the stalest heuristic's eps:0.3 data on
    lambda-300: a policy whose action depends on the state, and none of the heuristics."""
    root = tmp_path_factory.mktemp("checkpoint")
    data = root / "lambda-300.uavds"
    run_cli(
        "collect", "--config", CONFIG, "--task", "lambda-300", "--policy", "eps:0.3",
        "--transitions", 400, "--seed", 5, "--out", data,
    )
    run_cli(
        "train", "--config", CONFIG, "--task", "lambda-300", "--algo", "cql",
        "--dataset", data, "--shots", 400, "--epochs", 60, "--seed", 2, "--out", root / "cql",
    )
    return root / "cql" / "final"


@pytest.fixture(scope="session")
def trained_bcq(run_cli, trained):
    """Discrete BCQ (two heads: Q-values and imitation logits) on the same shots as `trained`."""
    root = trained.parent.parent
    run_cli(
        "train", "--config", CONFIG, "--task", "lambda-300", "--algo", "bcq",
        "--dataset", root / "lambda-300.uavds", "--shots", 400, "--epochs", 30, "--seed", 2,
        "--out", root / "bcq",
    )
    return root / "bcq" / "final"
