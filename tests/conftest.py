"""Shared fixtures."""

from __future__ import annotations

import contextlib
import os
import random
import selectors
import signal
import subprocess
import sys
import time
import uuid
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import psycopg
import pytest
import yaml

from agent.config import SACConfig, TrialConfig
from sweeper.storage import curve_of

ROOT = Path(__file__).resolve().parent.parent
CI_SPEC = ROOT / "studies" / "ci.yaml"
PG_ADMIN = "host=127.0.0.1 port=5432 dbname=test user=postgres"
#: a SAC small enough that a trial of a few hundred steps takes seconds
TINY_SAC = SACConfig(hidden_sizes=(16, 16), batch_size=16, updates_per_step=1, feature_dim=8,
                     num_filters=8)  # fmt: skip


def tiny(**changes: Any) -> TrialConfig:
    """A point_reach trial of 200 steps at 32x32 with ``TINY_SAC``, ``changes`` on top."""
    base = dict(
        env="point_reach",
        image_size=32,
        sac=TINY_SAC,
        total_steps=200,
        seed_steps=50,
        eval_every=100,
        eval_episodes=2,
        device="cpu",
    )
    return TrialConfig(**{**base, **changes})


#: a finished study, as published (its spec: studies/fetch_reach_cpu.yaml)
PUBLISHED = ROOT / "docs" / "studies" / "fetch_reach_cpu"
#: how ``damage`` can damage an SQLite file
DAMAGE = ["truncated", "not a database", "overwritten"]


def damage(path: Path, how: str) -> None:
    """Damage the SQLite file ``path`` as ``how`` (one of ``DAMAGE``) says."""
    data = path.read_bytes()
    if how == "truncated":
        path.write_bytes(data[: len(data) // 3])
    elif how == "not a database":
        path.write_bytes(b"this is not a database\n" * 200)
    else:  # two pages in the middle overwritten, as a stray write or a bad disk leaves it
        middle = len(data) // 2 // 4096 * 4096
        garbage = random.Random(0).randbytes(8192)
        path.write_bytes(data[:middle] + garbage + data[middle + len(garbage) :])


def write_ci_spec(path: Path, **changes: Any) -> Path:
    """studies/ci.yaml with top-level fields replaced (``execution`` and ``budget`` merged
    into the CI spec's own), written to ``path``."""
    data = yaml.safe_load(CI_SPEC.read_text())
    for name in ("execution", "budget"):
        data[name] = {**data[name], **changes.pop(name, {})}
    data.update(changes)
    path.write_text(yaml.safe_dump(data))
    return path


def wait_until(
    condition: Callable[[], Any], timeout: float, what: str, interval: float = 0.05
) -> Any:
    """Poll ``condition`` until it returns something true, and return that; an
    AssertionError naming ``what`` after ``timeout`` seconds."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = condition()
        if value:
            return value
        time.sleep(interval)
    raise AssertionError(f"timed out after {timeout} s waiting for {what}")


def assert_uninterrupted_curve(trial: Any, config: TrialConfig) -> None:
    """``trial``'s recorded curve, AUC and intermediate values are those of ``config`` run
    straight through (no checkpoints): what a resumed or paused trial must give on CPU."""
    import dataclasses

    import torch

    from agent import train

    torch.set_num_threads(1)
    reference = train(dataclasses.replace(config, checkpoint_dir=None, stop_at=None))
    curve = curve_of(trial)
    assert curve["step"] == list(reference.steps)
    for name, values in reference.metrics.items():
        assert curve[name] == list(values), name
    if trial.value is not None:  # a PRUNED trial keeps no value
        assert trial.value == reference.auc
    assert trial.intermediate_values == dict(
        zip(reference.steps, reference.metrics["success_rate"], strict=True)
    )


@dataclass(frozen=True)
class CIStudy:
    """The CI study after ``sweeper launch``: run the CLI from ``workdir`` with
    ``--storage storage_url`` to reach it."""

    spec: Path
    storage_url: str
    workdir: Path


@pytest.fixture(scope="session")
def ci_study(tmp_path_factory: pytest.TempPathFactory) -> CIStudy:
    """``sweeper launch studies/ci.yaml`` run once per session, in a fresh working directory
    (its runs/ folder) with an SQLite storage there. Tests may read the study and add to
    it (aggregate, dashboard notes) but must not relaunch or delete it."""
    workdir = tmp_path_factory.mktemp("ci_study")
    url = f"sqlite:///{workdir / 'study.db'}"
    env = {**os.environ, "PYTHONPATH": str(ROOT), "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")}
    command = [sys.executable, "-m", "sweeper.cli", "launch", str(CI_SPEC), "--storage", url]
    done = subprocess.run(
        command, cwd=workdir, env=env, capture_output=True, text=True, timeout=900
    )
    assert done.returncode == 0, f"sweeper launch failed:\n{done.stdout}\n{done.stderr[-4000:]}"
    return CIStudy(CI_SPEC, url, workdir)


@contextlib.contextmanager
def running_dashboard(study: CIStudy, timeout: float = 120) -> Iterator[str]:
    """``sweeper dashboard`` on ``study`` on a free port; yields the page address it prints
    (``http://127.0.0.1:PORT/dashboard/studies/ID``); on exit SIGTERM must stop it cleanly."""
    command = [sys.executable, "-m", "sweeper.cli", "dashboard", str(study.spec)]
    command += ["--storage", study.storage_url, "--port", "0"]
    process = subprocess.Popen(
        command,
        cwd=study.workdir,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        selector = selectors.DefaultSelector()
        selector.register(process.stdout, selectors.EVENT_READ)
        ready = wait_until(
            lambda: selector.select(timeout=1.0) or process.poll() is not None,
            timeout,
            "the dashboard's address",
        )
        line = process.stdout.readline() if ready and process.poll() is None else ""
        if not line:
            pytest.fail(f"no address from `sweeper dashboard`: {process.stderr.read()[-2000:]}")
        yield line.split()[1]  # "optuna-dashboard: http://127.0.0.1:PORT/dashboard/studies/ID"
    finally:
        process.send_signal(signal.SIGTERM)
        assert process.wait(timeout=30) == 0  # SIGTERM stops it cleanly


@pytest.fixture(scope="session")
def ci_aggregate(ci_study: CIStudy) -> Path:
    """``sweeper aggregate studies/ci.yaml`` run once, from the CI study's working directory
    (so to its default output folder, which is returned); it also saves the comparison
    figures and note into the study for optuna-dashboard."""
    from sweeper import cli

    here = os.getcwd()
    os.chdir(ci_study.workdir)
    try:
        code = cli.main(["aggregate", str(ci_study.spec), "--storage", ci_study.storage_url])
    finally:
        os.chdir(here)
    assert code == 0, "sweeper aggregate studies/ci.yaml failed"
    return ci_study.workdir / "runs" / "ci" / "aggregate"


@pytest.hookimpl(tryfirst=True)  # before xdist reads the groups
def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """``./run tests`` spreads the tests over two processes (``-n 2 --dist loadgroup``): the
    tests of the CI study run on one worker, so it is launched once, and a module's tests
    that share a module fixture (a local Ray) stay together, so it is started once: with
    the CI study's tests where their module has some."""

    def uses_ci_study(item: pytest.Item) -> bool:
        return bool({"ci_study", "ci_aggregate"} & set(item._fixtureinfo.name2fixturedefs))

    with_ci_study = {item.module.__name__ for item in items if uses_ci_study(item)}
    for item in items:
        fixtures = item._fixtureinfo.name2fixturedefs
        module = item.module.__name__
        if uses_ci_study(item):
            item.add_marker(pytest.mark.xdist_group("ci_study"))
        elif any(defs[-1].scope == "module" for defs in fixtures.values()):
            group = "ci_study" if module in with_ci_study else module
            item.add_marker(pytest.mark.xdist_group(group))


@pytest.fixture(scope="module")
def local_ray():
    """One local Ray for a module, its address returned: in-process drivers (``launch``)
    use it and leave it running, subprocess drivers join it with ``--address``."""
    import ray

    context = ray.init(address="local", num_cpus=2, include_dashboard=False, log_to_driver=False)
    yield context.address_info["address"]
    ray.shutdown()


@pytest.fixture
def pg_url():
    """A fresh PostgreSQL schema on the local server, dropped afterwards."""
    schema = f"sweeper_test_{uuid.uuid4().hex[:10]}"
    with psycopg.connect(PG_ADMIN, autocommit=True) as connection:
        connection.execute(f"CREATE SCHEMA {schema}")
    yield f"postgresql://postgres@127.0.0.1:5432/test?options=-csearch_path%3D{schema}"
    with psycopg.connect(PG_ADMIN, autocommit=True) as connection:
        connection.execute(f"DROP SCHEMA {schema} CASCADE")
