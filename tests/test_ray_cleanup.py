"""A launch's own local Ray (issue 22): Ray's noise stays out of its output (the token
authentication warning, the raylet's text on a dead worker; sweeper's own line stays), and
no Ray or worker process outlives its driver, after a clean exit or a SIGKILL.

Each driver runs in its own session (``start_new_session``), so its processes, Ray's
included, are found by their session id, which they keep when they are reparented to init.
"""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import ROOT, wait_until, write_ci_spec

DRIVER = """
import os, signal, sys, time
from pathlib import Path
from agent.config import TrialResult
from sweeper.run._launch import launch, prepare

spec_path, marker, mode = sys.argv[1], Path(sys.argv[2]), sys.argv[3]

def trial(config, report=None):
    report(0, {"success_rate": 0.0, "final_distance": 1.0})
    if mode == "hold":
        time.sleep(600)
    if not marker.exists():  # the first attempt's worker dies
        marker.touch()
        os.kill(os.getpid(), signal.SIGKILL)
    metrics = {"success_rate": (0.0, 1.0), "final_distance": (1.0, 0.0)}
    return TrialResult(steps=(0, config.total_steps), metrics=metrics, auc=0.5)

# the project's modules loaded when the driver loop starts (see the exit-0 test)
from sweeper.run import _driver as driver
started, run = [], driver.Driver.run
driver.Driver.run = lambda self, todo: started.append(set(sys.modules)) or run(self, todo)
spec, plan = prepare(spec_path)
code = launch(spec, plan, train=trial)
late = set(sys.modules) - started[0]
ours = sorted(m for m in late if m.split(".")[0] in ("agent", "sweeper"))
print("imported late:", ours, "agent.checkpoint" in started[0])
sys.exit(code)
"""


def session_processes(sid: int) -> dict[int, str]:
    """pid -> command line of the live (not zombie) processes of session ``sid``."""
    found = {}
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat = (entry / "stat").read_text()
            command = (entry / "cmdline").read_bytes().replace(b"\0", b" ").decode().strip()
        except OSError:
            continue
        fields = stat[stat.rfind(")") + 2 :].split()
        if fields[0] != "Z" and int(fields[3]) == sid:
            found[int(entry.name)] = command
    return found


def start_driver(tmp_path: Path, mode: str) -> subprocess.Popen:
    """A driver of a one-trial CI study that starts its own local Ray, in its own session;
    its trial dies once then finishes (``die``), or runs for minutes (``hold``)."""
    spec = write_ci_spec(
        tmp_path / "spec.yaml",
        study="cleanup",
        methods={"pixel": {}},
        storage=f"sqlite:///{tmp_path / 'study.db'}",
        checkpoints=str(tmp_path / "checkpoints"),
        random_episodes=0,
    )
    (tmp_path / "driver.py").write_text(DRIVER)
    env = {k: v for k, v in os.environ.items() if not k.startswith("RAY_")}  # Ray's defaults
    env["PYTHONPATH"] = str(ROOT)
    command = [sys.executable, "driver.py", str(spec), str(tmp_path / "died"), mode]
    return subprocess.Popen(
        command,
        cwd=tmp_path,
        env=env,
        stdout=(tmp_path / "out.log").open("w"),
        stderr=subprocess.STDOUT,
        start_new_session=True,
    )


def kill_session(sid: int) -> None:
    """SIGKILL what is left of a test's driver session (its processes only)."""
    for pid in session_processes(sid):
        with contextlib.suppress(OSError):
            os.kill(pid, signal.SIGKILL)


@pytest.mark.slow
def test_a_launch_prints_none_of_rays_noise_and_leaves_no_process_after_exit_0(tmp_path):
    """And the driver imports none of the project's code once its loop runs: code changed
    under a running launch (a git pull) was otherwise loaded half new, half old (the new
    ``sweeper.results`` imported after a trial beside the old ``sweeper.storage``), which
    stopped a study with an ImportError; the stop path's ``saved_step`` is loaded too."""
    driver = start_driver(tmp_path, "die")
    try:
        assert driver.wait(timeout=240) == 0, (tmp_path / "out.log").read_text()
        left = session_processes(driver.pid)  # at once: the launch waited for its Ray to go
    finally:
        kill_session(driver.pid)
    out = (tmp_path / "out.log").read_text()
    assert left == {}, f"left after exit 0: {left}\n{out}"
    assert "pixel/0/0: worker lost (ActorDiedError" in out  # sweeper's own line stays
    assert "re-running" in out and "pixel/0/0 completed" in out
    assert "Token authentication" not in out, out
    assert "A worker died" not in out and "(raylet)" not in out, out
    assert "imported late: [] True" in out, out


@pytest.mark.slow
def test_no_ray_process_outlives_a_driver_killed_with_sigkill(tmp_path):
    driver = start_driver(tmp_path, "hold")
    try:

        def trial_running() -> bool:
            commands = " ".join(session_processes(driver.pid).values())
            ready = all(
                name in commands
                for name in ("ray::DashboardAgent", "ray::RuntimeEnvAgent", "ray::TrialWorker")
            )
            return ready and "0 of 1 trials done, 1 to run" in (tmp_path / "out.log").read_text()

        wait_until(trial_running, 180, "the driver's Ray up and its trial running")
        os.kill(driver.pid, signal.SIGKILL)
        driver.wait(timeout=30)
        try:  # Ray's agents, left alone, waited 60 s for the dead GCS, reparented to init
            wait_until(lambda: not session_processes(driver.pid), 20, "no process left")
        except AssertionError:
            pytest.fail(f"left 20 s after the driver's SIGKILL: {session_processes(driver.pid)}")
    finally:
        kill_session(driver.pid)
