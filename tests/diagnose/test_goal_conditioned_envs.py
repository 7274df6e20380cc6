"""Diagnosis refuses goal-conditioned (Dict-observation) envs with a clear error, not a traceback."""

from __future__ import annotations

import pytest

from offdyn_bench.diagnose.data import DiagnosisInputError
from offdyn_bench.diagnose.source import SourceSimulator


def test_an_antmaze_source_is_refused_clearly():
    with pytest.raises(DiagnosisInputError, match=r"goal-conditioned \(Dict\) observations; diagnosis supports "
                                                  r"envs with one Box observation \(not AntMaze yet\)"):
        SourceSimulator("offdyn/AntMazeSmall-layout-blocked-source-v0")
