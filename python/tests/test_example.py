"""examples/python_quickstart.py runs as a user runs it."""

import subprocess
import sys

from conftest import REPO


def test_the_quickstart_example_runs(tmp_path):
    png = tmp_path / "world.png"
    out = subprocess.run(
        [sys.executable, str(REPO / "examples" / "python_quickstart.py"), "--png", str(png)],
        capture_output=True, text=True, cwd=tmp_path,
    )
    assert out.returncode == 0, out.stderr
    assert "stalest: return" in out.stdout and "random policy over 4096 episodes" in out.stdout
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
