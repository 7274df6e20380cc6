"""Gap diagnosis: find the residual of a source simulator on measured data, trace it to the effect
the simulator lacks, add that effect, and report the error before and after.

``diagnose(env_id, data)`` runs the loop; ``offdyn-bench diagnose`` is its command line. The
names load their module on first use, so the command line's help does not import the fitting
machinery (``mujoco.sysid``, scipy).
"""

from __future__ import annotations

import importlib
from typing import Any

_EXPORTS = {
    "diagnose": "offdyn_bench.diagnose.loop", "Diagnosis": "offdyn_bench.diagnose.loop",
    "DiagnosisSettings": "offdyn_bench.diagnose.loop", "Errors": "offdyn_bench.diagnose.loop",
    "Step": "offdyn_bench.diagnose.loop",
    "Transitions": "offdyn_bench.diagnose.data", "load_transitions": "offdyn_bench.diagnose.data",
    "load_npz": "offdyn_bench.diagnose.data", "load_minari": "offdyn_bench.diagnose.data",
    "DiagnosisInputError": "offdyn_bench.diagnose.data",
}

__all__ = [
    "diagnose", "Diagnosis", "DiagnosisSettings", "Errors", "Step",
    "Transitions", "load_transitions", "load_npz", "load_minari", "DiagnosisInputError",
]


def __getattr__(name: str) -> Any:
    if name in _EXPORTS:
        value = getattr(importlib.import_module(_EXPORTS[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'offdyn_bench.diagnose' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_EXPORTS))
