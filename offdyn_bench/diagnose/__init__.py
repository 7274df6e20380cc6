"""Gap diagnosis: find the residual of a source simulator on measured data, trace it to the effect
the simulator lacks, add that effect, and report the error before and after.

``diagnose(env_id, data)`` runs the loop; ``offdyn-bench diagnose`` is its command line.
"""

from offdyn_bench.diagnose.data import DiagnosisInputError, Transitions, load_minari, load_npz, load_transitions
from offdyn_bench.diagnose.loop import Diagnosis, DiagnosisSettings, Errors, Step, diagnose

__all__ = [
    "diagnose", "Diagnosis", "DiagnosisSettings", "Errors", "Step",
    "Transitions", "load_transitions", "load_npz", "load_minari", "DiagnosisInputError",
]
