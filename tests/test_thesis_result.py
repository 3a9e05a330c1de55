"""benchmarks/thesis_result.py: the verdict rule on the thesis' claims (the README's table)."""

from __future__ import annotations

import importlib.util
import math

from conftest import ROOT

_spec = importlib.util.spec_from_file_location(
    "thesis_result", ROOT / "benchmarks" / "thesis_result.py"
)
thesis_result = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(thesis_result)


def test_a_claim_holds_only_when_every_interval_lies_above_one_half():
    judge = thesis_result.judge
    assert judge([(0.6, 0.9), (0.51, 1.0)]) == "holds"
    assert judge([(0.6, 0.9), (0.5, 1.0)]) == "not settled"  # 0.5 itself: a tie is possible
    assert judge([(0.6, 0.9), (0.0, 0.49)]) == "contradicted"  # one clearly behind
    assert judge([(0.2, 0.8)]) == "not settled"
    assert judge([]) == "not settled"  # no pair of trials
    assert judge([(math.nan, math.nan)]) == "not settled"
