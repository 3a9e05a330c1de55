"""ruff stays clean on the whole tree, lint and format, and the import contracts of
``lint-imports`` hold (both configured in pyproject.toml)."""

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import ROOT


@pytest.mark.parametrize("command", [["check"], ["format", "--check"]], ids=["check", "format"])
def test_ruff_is_clean(command):
    ruff = shutil.which("ruff") or str(Path(sys.executable).parent / "ruff")
    result = subprocess.run([ruff, *command, str(ROOT)], capture_output=True, text=True)
    assert result.returncode == 0, result.stdout + result.stderr


def lint_imports(root: Path) -> subprocess.CompletedProcess:
    """``lint-imports`` on the tree at ``root``, with its contracts (pyproject.toml)."""
    command = shutil.which("lint-imports") or str(Path(sys.executable).parent / "lint-imports")
    env = {**os.environ, "PYTHONPATH": str(root)}
    # --no-cache: the suite leaves nothing in the checkout (.ci/run checks)
    return subprocess.run(
        [command, "--no-cache"], cwd=root, env=env, capture_output=True, text=True
    )


def test_the_layers_of_docs_architecture_hold():
    result = lint_imports(ROOT)
    assert result.returncode == 0, result.stdout + result.stderr
    assert "0 broken" in result.stdout


@pytest.mark.parametrize(
    ("module", "line", "contract"),
    [
        ("sweeper/spec/_words.py", "import sweeper.storage", "sweeper's packages"),
        ("sweeper/results/_stats.py", "import sweeper.run._launch", "sweeper's packages"),
        ("agent/metrics.py", "import sweeper.spec", "sweeper -> agent -> encoders"),
        ("sweeper/run/_reaper.py", "import sweeper.run._launch", "no import circle"),
    ],
)
def test_a_backwards_import_breaks_a_contract(tmp_path, module, line, contract):
    """Each contract fails on the import it forbids (in a copy of the tree)."""
    for name in ("pyproject.toml", "agent", "encoders", "sweeper"):
        source = ROOT / name
        if source.is_dir():
            shutil.copytree(source, tmp_path / name, ignore=shutil.ignore_patterns("__pycache__"))
        else:
            shutil.copy(source, tmp_path / name)
    path = tmp_path / module
    path.write_text(path.read_text() + f"\n{line}  # noqa\n")
    result = lint_imports(tmp_path)
    assert result.returncode != 0
    broken = [row for row in result.stdout.splitlines() if row.endswith(" BROKEN")]
    assert [row for row in broken if row.startswith(contract)], result.stdout
