"""``sweeper rerun``'s comparison and what it says of the machines (the command itself runs
at the end of test_launch's end-to-end test, on the CI study it launched)."""

from __future__ import annotations

import math

from sweeper.run.cli_rerun import (
    difference_at,
    first_difference,
    machine_lines,
    recorded_layout,
    recorded_threads,
)

CURVE = {"step": [0, 100], "success_rate": [0.0, 0.5], "final_distance": [0.3, math.nan]}
HERE = {"cpu": "AuthenticAMD 26 2", "cpu_name": "AMD EPYC", "kernels": "AVX512", "torch": "2",
        "conv_layout": "channels_last", "threads": "1"}  # fmt: skip


def test_curves_are_compared_float_for_float_nan_equal_to_nan():
    assert first_difference(CURVE, dict(CURVE)) is None
    off = {**CURVE, "final_distance": [0.30000000000000004, math.nan]}
    assert first_difference(CURVE, off) == (
        "step 0, final_distance: 0.30000000000000004 (recorded: 0.3)"
    )
    later = {**CURVE, "success_rate": [0.0, 0.6]}
    assert first_difference(CURVE, later) == "step 100, success_rate: 0.6 (recorded: 0.5)"
    assert "evaluation steps" in first_difference(CURVE, {**CURVE, "step": [0, 50]})
    missing = {k: v for k, v in CURVE.items() if k != "final_distance"}
    assert first_difference(CURVE, missing) == "no final_distance (recorded: 0.3)"
    # a metric the record does not hold (a newer agent's) is not compared
    assert first_difference(CURVE, {**CURVE, "new": [1.0, 1.0]}) is None


def test_one_evaluation_is_compared_with_the_recorded_one_at_its_step():
    assert difference_at(CURVE, 100, {"success_rate": 0.5, "final_distance": math.nan}) is None
    assert difference_at(CURVE, 0, {"success_rate": 0.0, "final_distance": 0.31}) == (
        "step 0, final_distance: 0.31 (recorded: 0.3)"
    )
    assert "does not hold" in difference_at(CURVE, 50, {"success_rate": 0.0})


def test_the_machines_say_whether_the_same_curve_is_to_be_expected():
    same = machine_lines([{"from_step": 0, **HERE}], HERE)
    assert same[-1] == "the same machine: the curve should be the recorded one"
    intel = {**HERE, "cpu": "GenuineIntel 6 143", "cpu_name": "Xeon"}
    other = machine_lines([{"from_step": 0, **intel}, {"from_step": 5000, **HERE}], HERE)
    assert other[0] == (
        "recorded on: Xeon (GenuineIntel 6 143), kernels AVX512, torch 2, conv layout "
        "channels_last, 1 thread (from step 0)"
    )
    assert other[-1].startswith("another machine (or unknown)")
    resumed = machine_lines([{"from_step": 5000, **HERE}], HERE)  # an older checkpoint's runs
    assert "the runs before step 5000 were not recorded" in resumed
    assert resumed[-1].startswith("another machine (or unknown)")
    # a record from before the layout was recorded ran channels-last
    older = {k: v for k, v in HERE.items() if k != "conv_layout"}
    assert machine_lines([{"from_step": 0, **older}], HERE)[-1].startswith("the same machine")
    nchw = {**HERE, "conv_layout": "nchw"}
    assert machine_lines([{"from_step": 0, **older}], nchw)[-1].startswith("another machine")
    # the same CPU at 2 threads splits its sums otherwise; before threads were recorded: the
    # re-run's (the spec's)
    two = {"from_step": 0, **HERE, "threads": "2"}
    assert machine_lines([two], HERE)[-1].startswith("another machine")
    assert machine_lines([two], {**HERE, "threads": "2"})[0].endswith(", 2 threads (from step 0)")
    # ... and one from before threads were recorded may have run at other threads: said so
    unthreaded = {k: v for k, v in HERE.items() if k != "threads"}
    assert machine_lines([{"from_step": 0, **unthreaded}], HERE)[-1].startswith(
        "the same machine if the trial ran at 1 torch thread, as this re-run does"
    )
    assert machine_lines([{"from_step": 0, **unthreaded}], nchw)[-1].startswith("another")
    unknown = machine_lines(None, HERE)
    assert unknown[0].startswith("recorded on: not recorded")


def test_a_rerun_takes_the_layout_of_the_trial_s_first_recorded_run():
    nchw = {"from_step": 0, **HERE, "conv_layout": "nchw"}
    assert recorded_layout([nchw, {"from_step": 5000, **HERE}]) == "nchw"
    older = {"from_step": 0, **{k: v for k, v in HERE.items() if k != "conv_layout"}}
    assert recorded_layout([older]) == "channels_last"  # before layouts were recorded
    assert recorded_layout(None) == "channels_last"  # before machines were recorded


def test_a_rerun_takes_the_threads_of_the_trial_s_first_recorded_run():
    two = {"from_step": 0, **HERE, "threads": "2"}
    assert recorded_threads([two, {"from_step": 5000, **HERE}], spec_threads=1) == 2
    older = {"from_step": 0, **{k: v for k, v in HERE.items() if k != "threads"}}
    assert recorded_threads([older], spec_threads=3) == 3  # before threads were recorded
    assert recorded_threads(None, spec_threads=1) == 1
