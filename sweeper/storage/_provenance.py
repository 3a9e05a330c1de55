"""Provenance of a study's results: the code's git revision and the installed versions
of the packages a result depends on, recorded by the driver as study user attrs
(``revision``, ``versions``).
"""

from __future__ import annotations

import subprocess
from importlib import metadata
from pathlib import Path

#: distributions whose versions the study records
VERSIONED_PACKAGES = (
    "gcrl-sweeper",
    "torch",
    "numpy",
    "mujoco",
    "gymnasium",
    "gymnasium-robotics",
    "metaworld",
    "optuna",
    "ray",
    "sqlalchemy",
)


def code_revision() -> str:
    """The git commit of this checkout (``-dirty`` if tracked files changed), or "unknown"."""
    root = Path(__file__).resolve().parents[2]
    try:
        commit = subprocess.run(
            ["git", "rev-parse", "HEAD"],
            cwd=root,
            capture_output=True,
            text=True,
            timeout=10,
        )
        if commit.returncode != 0:
            return "unknown"
        dirty = subprocess.run(
            ["git", "diff", "--quiet", "HEAD"],
            cwd=root,
            capture_output=True,
            timeout=10,
        )
    except (OSError, subprocess.TimeoutExpired):
        return "unknown"
    return commit.stdout.strip() + ("-dirty" if dirty.returncode == 1 else "")


def package_versions() -> dict[str, str]:
    """Installed versions of the packages a result depends on."""
    versions = {}
    for name in VERSIONED_PACKAGES:
        try:
            versions[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            versions[name] = "not installed"
    return versions
