"""The fixed evaluation protocol (``PROTOCOL.md`` at the top of the repository is its prose).

* :mod:`~offdyn_bench.protocol.definition`: the version, tracks, budgets, evaluation episodes and
  seeds, the core suite, the official target and source datasets of a task on a track;
* :mod:`~offdyn_bench.protocol.references`: reference scores with provenance
  (``assets/reference_scores.json``) and the normalized score;
* :mod:`~offdyn_bench.protocol.statistics`: IQM, stratified-bootstrap intervals, optimality gap,
  probability of improvement, performance profiles.

``reference_scores()`` maps a task to ``{"random": ..., "oracle/<budget>": ...}``: the oracle is
``sac-target`` at the same budget, so it is kept per budget. ``normalized_score(returns, task,
budget)`` raises :class:`ProtocolError` while a task lacks either reference.

Nothing heavy is imported here: the CLI imports this module to start.
"""

from offdyn_bench.protocol.definition import (
    BUDGETS,
    CORE_SUITE,
    EPISODE_SEEDS,
    EVAL_EPISODES,
    MIN_SEEDS,
    PROTOCOL_VERSION,
    REFERENCE_METHODS,
    TRACKS,
    Budget,
    ProtocolError,
    Track,
    check_method_on_track,
    get_budget,
    get_track,
    official_dataset,
    official_datasets,
    official_source_dataset,
    track_of_method,
)
from offdyn_bench.protocol.references import (
    REFERENCE_FILE,
    ReferenceScore,
    has_references,
    normalized_score,
    record_oracle_reference,
    record_random_reference,
    record_zero_command_reference,
    reference_pair,
    reference_scores,
)

__all__ = [
    "BUDGETS", "CORE_SUITE", "EPISODE_SEEDS", "EVAL_EPISODES", "MIN_SEEDS", "PROTOCOL_VERSION",
    "REFERENCE_FILE", "REFERENCE_METHODS", "TRACKS", "Budget", "ProtocolError", "ReferenceScore", "Track",
    "check_method_on_track", "get_budget", "get_track", "has_references", "normalized_score",
    "official_dataset", "official_datasets", "official_source_dataset", "record_oracle_reference",
    "record_random_reference",
    "record_zero_command_reference", "reference_pair",
    "reference_scores", "track_of_method",
]
