"""Every example of docs/PYTHON.md runs as written in a fresh checkout: the page's `uavmeta`
commands make the files it reads, then its Python blocks run in order in one interpreter (a
reader following the page), from a directory holding only what a checkout holds (configs/)."""

import os
import re
import shutil
import subprocess
import sys

from conftest import REPO

DOC = REPO / "docs" / "PYTHON.md"


def blocks(kind):
    return re.findall(rf"^```{kind}\n(.*?)^```", DOC.read_text(), re.S | re.M)


def test_the_page_has_commands_and_python_examples():
    commands = [line for b in blocks("sh") for line in b.splitlines() if line.startswith("uavmeta ")]
    assert len(commands) == 2 and len(blocks("python")) == 6


def test_every_example_of_docs_python_runs_as_written(uavmeta_bin, tmp_path):
    shutil.copytree(REPO / "configs", tmp_path / "configs")
    for block in blocks("sh"):
        for line in block.splitlines():
            # Install lines (pip, make) are what made this test's package; the rest must run.
            if not line.strip() or line.lstrip().startswith("#"):
                continue
            if line.startswith("uavmeta "):
                argv = [uavmeta_bin, *line.split()[1:]]
                out = subprocess.run(argv, cwd=tmp_path, capture_output=True, text=True)
                assert out.returncode == 0, (line, out.stderr)
            else:
                assert re.match(r"(pip|make) ", line), f"a command the test does not run: {line}"
    script = "\n\n".join(blocks("python"))
    (tmp_path / "page.py").write_text(script)
    # TMPDIR: SB3's default logger makes a folder there that nobody removes; pytest removes tmp_path.
    env = {**os.environ, "TMPDIR": str(tmp_path)}
    out = subprocess.run([sys.executable, "page.py"], cwd=tmp_path, capture_output=True, text=True,
                         env=env)
    assert out.returncode == 0, out.stderr
    assert "'task_id': 0, 'lam': 300.0" in out.stdout
    assert (tmp_path / "runs" / "quick" / "tuned.json").exists()
