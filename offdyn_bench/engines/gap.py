"""What a gap diagnosis should say about data recorded on another physics engine."""

from __future__ import annotations

from offdyn_bench.errors import OffdynError

ENGINE_NAMES = {"dart": "DART"}


def engine_gap_note(recorded_env_id: str | None) -> str | None:
    """A plain note for a diagnosis report when ``recorded_env_id`` (the env a dataset names: a
    task's source id) belongs to a pair whose target runs on another engine; ``None`` otherwise.

    The effect vocabulary edits MuJoCo models: it cannot express hard LCP contacts, another
    constraint solver or another integrator, so a residual is expected to remain."""
    if not recorded_env_id:
        return None
    from offdyn_bench.tasks import get_task

    try:
        pair = get_task(recorded_env_id)
    except OffdynError:
        return None
    if pair.target_engine == "mujoco":
        return None
    engine = ENGINE_NAMES.get(pair.target_engine, pair.target_engine)
    return (f"the data were recorded in {pair.env_id('target')}, which runs on {engine}, not MuJoCo: its contact "
            "model, constraint solver and integrator lie outside the effect vocabulary, so part of the residual is "
            "an engine gap that no effect can explain")
