"""The tree passes its ruff configuration (pyproject.toml: pyflakes, import order, heavy imports only where allowed;
ruff comes with the test extra)."""
import subprocess
import sys

from sims.scene.config import REPO_ROOT


def test_ruff_finds_nothing():
    result = subprocess.run([sys.executable, "-m", "ruff", "check", "--no-cache", "."], cwd=REPO_ROOT, capture_output=True, text=True)
    assert result.returncode == 0, result.stdout + result.stderr
