"""Workers that can never start stop the launch with one line, instead of being replaced
forever (found when a test's fake trial could not be unpickled in the workers)."""

from __future__ import annotations

import io
import sys

import ray
from conftest import write_ci_spec

from sweeper.run._launch import launch, prepare

ray.cloudpickle.register_pickle_by_value(sys.modules[__name__])  # Unloadable, by value


def _refuse_to_load():
    raise ModuleNotFoundError("No module named 'only_on_the_driver'")


class Unloadable:
    """A ``train`` that the workers cannot unpickle: every actor dies while starting."""

    def __reduce__(self):
        return (_refuse_to_load, ())

    def __call__(self, config, report=None):  # never reached
        raise AssertionError("a worker ran a trial")


def test_workers_that_cannot_start_exit_2_with_the_cause(tmp_path, local_ray):
    url = f"sqlite:///{tmp_path / 'study.db'}"
    spec, plan = prepare(str(write_ci_spec(tmp_path / "ci.yaml", storage=url, random_episodes=0)))
    stream = io.StringIO()
    assert launch(spec, plan, train=Unloadable(), stream=stream) == 2
    last = stream.getvalue().strip().splitlines()[-1]
    assert last.startswith("sweeper launch: the trial workers failed to start 5 times in a row")
    assert "No module named 'only_on_the_driver'" in last
