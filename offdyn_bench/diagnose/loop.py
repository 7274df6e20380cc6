"""The diagnosis loop: residual, trace, add, repeat; then say what is left.

1. Residual of the current hypothesis (one step and ``horizon`` steps open loop) and the noise floor.
2. Screen every candidate of the library, fit the best few, validate each on held-out episodes.
3. Add the one that lowers held-out error most (significantly, and by more than the complexity
   penalty), refit the effects added before it, and repeat until the held-out error reaches the
   noise floor or nothing helps.
"""

from __future__ import annotations

import dataclasses
import os
import time
from typing import Any

import numpy as np

from offdyn_bench.diagnose.candidates import (
    DISTINGUISHING,
    Candidate,
    candidate_library,
)
from offdyn_bench.diagnose.data import Transitions, load_transitions
from offdyn_bench.diagnose.identifiability import Identifiability, identifiability
from offdyn_bench.diagnose.residual import (
    NUMERICAL_FLOOR,
    SEARCH_TARGETS,
    ErrorSummary,
    Hypothesis,
    ObservationCheck,
    ResidualEvaluator,
    SearchTarget,
    block_improvement_z,
)
from offdyn_bench.diagnose.search import Fit, fit, screen
from offdyn_bench.diagnose.source import SourceSimulator
from offdyn_bench.diagnose.stochastic import action_channel_share, estimate_action_noise
from offdyn_bench.diagnose.systematic import (
    Predictability,
    horizon_under_action_noise,
    residual_predictability,
)
from offdyn_bench.engines.gap import engine_gap_note
from offdyn_bench.errors import InvalidParameterError
from offdyn_bench.json_values import is_integer, is_number
from offdyn_bench.versions import versions

# The H-step error needs a window of H steps inside one episode; Gymnasium's MuJoCo tasks end
# episodes at 1000 steps, so a longer horizon could never be measured.
MAX_HORIZON = 1000
MAX_EFFECTS = 20


@dataclasses.dataclass(frozen=True)
class DiagnosisSettings:
    """Knobs of the loop; the defaults are what the CLI and the tests use."""

    horizon: int = 10
    """H of the H-step open-loop error."""
    search_horizon: int = 1
    """Steps ahead the search compares (screen, fits, held-out choice, the stop at the floor). One
    suits most data; at a high control rate with noisy sensors, where one step moves the state less
    than the noise, a longer horizon lets effects add up above it."""
    max_effects: int = 4
    """At most this many effects are added."""
    fit_top: int = 5
    """How many screened candidates are fitted per iteration."""
    fit_score_ratio: float = 0.2
    """Only candidates whose screening score is at least this fraction of the best are fitted."""
    min_relative_gain: float = 0.02
    """Complexity penalty: an added parameter must cut held-out squared error by this fraction."""
    min_z: float = 3.0
    """Significance: the held-out gain must exceed this many block standard errors."""
    floor_tolerance: float = 1e-3
    """Absolute slack (normalized units) added to the noise floor in the two tests below."""
    search_margin: float = 0.02
    """The search stops once the held-out error is within this fraction above the floor."""
    explained_margin: float = 0.1
    """A final held-out error within this fraction above the floor leaves no unexplained residual."""
    heldout_fraction: float = 0.3
    search_target: SearchTarget = "auto"
    """What the search compares predictions with: ``observations`` (the recorded ones), ``states``
    (the observation read off the stored state: the dynamics without the sensors, whose delay and
    offset are then read off the two recordings' difference), or ``auto``: the stored states where
    the data have them and the sensors differ from them, the observations otherwise."""
    screen_rows: int = 600
    fit_rows: int = 1500
    seed: int = 0

    def __post_init__(self) -> None:
        integers = {"horizon": (1, MAX_HORIZON), "search_horizon": (1, MAX_HORIZON), "max_effects": (0, MAX_EFFECTS), "fit_top": (1, 100),
                    "screen_rows": (10, 10**6), "fit_rows": (10, 10**6), "seed": (0, 2**32 - 1)}
        for name, (low, high) in integers.items():
            value = getattr(self, name)
            if not is_integer(value) or not low <= value <= high:
                raise InvalidParameterError("diagnosis settings", name, value, f"an integer in [{low}, {high}]")
        if self.search_target not in SEARCH_TARGETS:
            raise InvalidParameterError("diagnosis settings", "search_target", self.search_target,
                                        f"one of {', '.join(SEARCH_TARGETS)}")
        fractions = {"fit_score_ratio": (0.0, 1.0), "min_relative_gain": (0.0, 1.0), "min_z": (0.0, 100.0),
                     "floor_tolerance": (0.0, 1.0), "search_margin": (0.0, 10.0), "explained_margin": (0.0, 10.0),
                     "heldout_fraction": (0.05, 0.95)}
        for name, (low, high) in fractions.items():
            value = getattr(self, name)
            if not is_number(value) or not low <= value <= high:
                raise InvalidParameterError("diagnosis settings", name, value, f"a number in [{low:g}, {high:g}]")


@dataclasses.dataclass(frozen=True)
class Errors:
    """Normalized RMSEs of one hypothesis. An H-step error is ``None`` (JSON ``null``: not
    measured) when no episode of that subset has a window of H steps; never 0.0, which would read
    as a perfect model."""

    one_step_nrmse: float
    heldout_one_step_nrmse: float
    horizon_nrmse: float | None
    heldout_per_dimension: tuple[float, ...]
    heldout_trimmed_nrmse: float
    heldout_horizon_nrmse: float | None

    def to_json(self) -> dict[str, float | None]:
        return {"one_step_nrmse": self.one_step_nrmse, "heldout_one_step_nrmse": self.heldout_one_step_nrmse,
                "horizon_nrmse": self.horizon_nrmse, "heldout_horizon_nrmse": self.heldout_horizon_nrmse,
                "heldout_trimmed_one_step_nrmse": self.heldout_trimmed_nrmse}


@dataclasses.dataclass(frozen=True)
class Step:
    """One iteration: the effect added and the error before and after it."""

    effect: dict[str, Any]
    interval: tuple[float, float]
    on_bound: bool
    before: Errors
    after: Errors
    heldout_gain_z: float
    equivalent_alternatives: tuple[str, ...]
    screened: tuple[tuple[str, float], ...]
    refitted: tuple[dict[str, Any], ...]
    stochastic: bool = False

    def to_json(self) -> dict[str, Any]:
        return {"effect": self.effect, "interval": list(self.interval), "on_bound": self.on_bound,
                "stochastic": self.stochastic,
                "error_before": self.before.to_json(), "error_after": self.after.to_json(),
                "heldout_gain_z": self.heldout_gain_z,
                "equivalent_alternatives": list(self.equivalent_alternatives),
                "screened": [{"candidate": c, "score": s} for c, s in self.screened],
                "refitted": list(self.refitted)}


@dataclasses.dataclass(frozen=True)
class Diagnosis:
    """The result of :func:`diagnose`; :meth:`to_json` is the public JSON contract."""

    env_id: str
    dataset: str
    transitions: int
    state_source: str
    notes: tuple[str, ...]
    effects_added: tuple[dict[str, Any], ...]
    error_before: Errors
    error_after: Errors
    noise_floor: float
    noise_floor_per_dimension: tuple[float, ...]
    unexplained_residual: bool
    stop_reason: str
    steps: tuple[Step, ...]
    calibrated_env: dict[str, Any]
    action_channel_share: float
    dimension_names: tuple[str, ...]
    timings: dict[str, float]
    residual_predictability: Predictability | None = None
    identifiability: Identifiability | None = None
    observation_check: dict[str, Any] = dataclasses.field(default_factory=dict)
    noise_floor_source: str = ""
    candidates_searched: int = 0
    search_horizon: int = 1

    def to_json(self) -> dict[str, Any]:
        return {
            "env_id": self.env_id,
            "dataset": self.dataset,
            "transitions": self.transitions,
            "state_source": self.state_source,
            "notes": list(self.notes),
            "effects_added": [dict(e) for e in self.effects_added],
            "error_before": self.error_before.to_json(),
            "error_after": self.error_after.to_json(),
            "noise_floor": self.noise_floor,
            "noise_floor_source": self.noise_floor_source,
            "candidates_searched": self.candidates_searched,
            "search_horizon": self.search_horizon,
            "observation_channel": self.observation_check,
            "unexplained_residual": self.unexplained_residual,
            "residual_predictability": (None if self.residual_predictability is None
                                        else self.residual_predictability.to_json()),
            "identifiability": None if self.identifiability is None else self.identifiability.to_json(),
            "stop_reason": self.stop_reason,
            "steps": [s.to_json() for s in self.steps],
            "calibrated_env": self.calibrated_env,
            "action_channel_share": self.action_channel_share,
            "per_dimension": {
                "names": list(self.dimension_names),
                "heldout_nrmse_before": list(self.error_before.heldout_per_dimension),
                "heldout_nrmse_after": list(self.error_after.heldout_per_dimension),
                "noise_floor": list(self.noise_floor_per_dimension),
            },
            "timings_s": self.timings,
            "versions": versions(),
        }


def _errors(evaluator: ResidualEvaluator, hypothesis: Hypothesis) -> Errors:
    summary = evaluator.summary(hypothesis)
    horizon, heldout_horizon = summary.get("horizon"), summary.get("horizon_heldout")
    return Errors(one_step_nrmse=summary["train"].nrmse, heldout_one_step_nrmse=summary["heldout"].nrmse,
                  horizon_nrmse=None if horizon is None else horizon.nrmse,
                  heldout_per_dimension=tuple(float(x) for x in summary["heldout"].per_dimension),
                  heldout_trimmed_nrmse=summary["heldout"].trimmed_nrmse,
                  heldout_horizon_nrmse=None if heldout_horizon is None else heldout_horizon.nrmse)


def _effect_json(candidate: Candidate, value: float) -> dict[str, Any]:
    """The effect as a report lists it: kind, target and fitted value first, then what tells two
    candidates of one kind apart (a joint's lower or upper limit, an axis)."""
    out: dict[str, Any] = {"kind": candidate.kind, "target": candidate.target,
                           "value": candidate.parameter_value(value)}
    out.update({k: v for k, v in candidate.fixed if k in DISTINGUISHING})
    return out


def _interval_json(candidate: Candidate, low: float, high: float) -> list[Any]:
    if candidate.search == "categorical":  # a category is located exactly, or not at all
        return [candidate.parameter_value(low), candidate.parameter_value(high)]
    return [float(low), float(high)]


def _search_summary(evaluator: ResidualEvaluator, hypothesis: Hypothesis) -> ErrorSummary:
    """The held-out error in the search's units (``search_horizon`` steps ahead)."""
    residual, = evaluator.search_residuals([hypothesis], "heldout")
    return ErrorSummary.of(residual)


def _at_floor(errors: ErrorSummary, floor: float, floor_dims: np.ndarray, settings: DiagnosisSettings,
              margin: float) -> bool:
    """Whether the held-out error (worst 1% of rows left out) is at the noise floor, overall and in
    every dimension. Per dimension because floors differ: where some sensors are noisy and others
    are not, the noisy ones dominate the overall figure and would hide a model error that only the
    quiet dimensions show. Each dimension gets three standard errors of its RMS estimate on top."""
    if errors.trimmed_nrmse > floor * (1.0 + margin) + settings.floor_tolerance + NUMERICAL_FLOOR:
        return False
    if not errors.rows:
        return True
    sampling = 3.0 / np.sqrt(2.0 * errors.rows)
    tolerance = settings.floor_tolerance * np.sqrt(len(floor_dims)) + NUMERICAL_FLOOR
    per_dim = np.asarray(errors.trimmed_per_dimension)
    return bool(np.all(per_dim <= floor_dims * (1.0 + margin + sampling) + tolerance))


def diagnose(env_id: str, data: Transitions | str | os.PathLike, settings: DiagnosisSettings | None = None,
             **env_kwargs: Any) -> Diagnosis:
    """Find the effects the source ``env_id`` lacks to explain ``data`` (transitions or a path /
    Minari id), add them, and report the error before and after."""
    settings = settings or DiagnosisSettings()
    clock = {"setup": 0.0, "screen": 0.0, "fits": 0.0, "validation": 0.0}
    started = time.perf_counter()
    source = SourceSimulator(env_id, **env_kwargs)
    if not isinstance(data, Transitions):
        data = load_transitions(data, nq=source.base_model.nq, nv=source.base_model.nv)
    evaluator = ResidualEvaluator(source, data, horizon=settings.horizon, heldout_fraction=settings.heldout_fraction,
                                  screen_rows=settings.screen_rows, fit_rows=settings.fit_rows, seed=settings.seed,
                                  search_horizon=settings.search_horizon, search_target=settings.search_target)
    check = evaluator.observation_check
    # Observation effects only where the stored states show the sensors disagree with the state;
    # none when the search runs on the stored states (the sensors are read off them directly).
    recorded_qpos = source.qpos_qvel(evaluator.states[evaluator.usable])[:, :source.base_model.nq]
    on_states = evaluator.search_on_states
    library = candidate_library(source, obs_bias_dims=() if on_states else check.bias_allowed,
                                obs_delay_dims=() if on_states else check.delay_allowed, qpos=recorded_qpos,
                                commands=evaluator.applied_actions(())[evaluator.usable])
    clock["setup"] = time.perf_counter() - started

    tick = time.perf_counter()
    hypothesis: Hypothesis = ()
    chosen: list[tuple[Candidate, float, tuple[float, float], bool]] = []
    history: dict[str, list[Any]] = {}  # each effect's value when added and after every refit
    first = _errors(evaluator, hypothesis)
    # Measured from the data once; no hypothesis judged against it may move it.
    floor, floor_dims = evaluator.noise_floor()
    search_floor, search_floor_dims = evaluator.search_floor()
    # A residual that a per-step command correction explains points at the action channel.
    share_before = action_channel_share(evaluator, hypothesis).share
    clock["validation"] += time.perf_counter() - tick
    current = first
    steps: list[Step] = []
    stop_reason = f"reached the limit of {settings.max_effects} effects"
    # The sensors, read off the stored states: their effects come first and stay as measured; the
    # search below works on the dynamics alone (``hypothesis``), and errors are reported for both.
    sensed: Hypothesis = ()
    sensed_chosen: list[Chosen] = []
    if on_states:
        tick = time.perf_counter()
        before_residual, = evaluator.residuals([sensed], "heldout")
        for candidate, value, interval in _sensor_effects(check):
            sensed = sensed + (candidate.effect(value),)
            sensed_chosen.append((candidate, value, interval, False))
            after_residual, = evaluator.residuals([sensed], "heldout")
            after = _errors(evaluator, sensed)
            steps.append(Step(effect=_effect_json(candidate, value), interval=interval, on_bound=False, before=current,
                              after=after, heldout_gain_z=float(min(block_improvement_z(before_residual, after_residual), 1e6)),
                              equivalent_alternatives=(), screened=((f"{candidate.label}: read off the stored states", 0.0),),
                              refitted=()))
            history[candidate.label] = [candidate.parameter_value(value)]
            current, before_residual = after, after_residual
        clock["validation"] += time.perf_counter() - tick

    for _ in range(settings.max_effects):
        # Searching on costs a screen; a model already this close to the floor has nothing left
        # that a significance test could find.
        if _at_floor(_search_summary(evaluator, hypothesis), search_floor, search_floor_dims, settings,
                     settings.search_margin):
            stop_reason = "held-out error reached the noise floor"
            break
        tick = time.perf_counter()
        scores = [s for s in screen(evaluator, hypothesis, library) if s.reduction > 0]
        clock["screen"] += time.perf_counter() - tick
        if not scores:
            stop_reason = "no candidate reduces the residual"
            break
        tick = time.perf_counter()
        # Candidates the screen scores far below the best cannot win; fitting them only costs time.
        promising = [s for s in scores[:settings.fit_top] if s.reduction >= settings.fit_score_ratio * scores[0].reduction]
        fits = [fit(evaluator, hypothesis, s.candidate, s.start) for s in promising]
        clock["fits"] += time.perf_counter() - tick

        tick = time.perf_counter()
        base, = evaluator.search_residuals([hypothesis], "heldout")
        trials = evaluator.search_residuals([hypothesis + (f.candidate.effect(f.value),) for f in fits], "heldout")
        base_sse = float(np.sum(base**2))
        gains = [(base_sse - float(np.sum(r**2))) / max(base_sse, 1e-300) for r in trials]
        z_scores = [block_improvement_z(base, r) for r in trials]
        clock["validation"] += time.perf_counter() - tick
        accepted = [i for i in range(len(fits)) if gains[i] >= settings.min_relative_gain and z_scores[i] >= settings.min_z]
        if not accepted:
            stop_reason = "no candidate improves held-out error significantly"
            break
        best_gain = max(gains[i] for i in accepted)
        # Candidates within 1% of the best gain explain the data equally: report the simplest kind.
        equivalent = [i for i in accepted if best_gain - gains[i] <= 0.01 * best_gain]
        pick = min(equivalent, key=lambda i: (fits[i].candidate.priority, -gains[i]))
        chosen_fit: Fit = fits[pick]
        alternatives = tuple(f"{fits[i].candidate.label} = {fits[i].value:.4g}" for i in equivalent if i != pick)

        hypothesis = hypothesis + (chosen_fit.candidate.effect(chosen_fit.value),)
        chosen.append((chosen_fit.candidate, chosen_fit.value, chosen_fit.interval, chosen_fit.on_bound))
        added = chosen_fit.candidate
        history.setdefault(added.label, []).append(added.parameter_value(chosen_fit.value))
        refitted: list[dict[str, Any]] = []
        if len(chosen) > 1:
            # Effects found earlier were fitted while this one was missing: refit every effect with
            # the others fixed (one coordinate pass, the newest last so it sees the refits).
            tick = time.perf_counter()
            for j in range(len(chosen)):
                candidate, value, _, _ = chosen[j]
                others = hypothesis[:j] + hypothesis[j + 1:]
                refit = fit(evaluator, others, candidate, value)
                chosen[j] = (candidate, refit.value, refit.interval, refit.on_bound)
                history[candidate.label].append(candidate.parameter_value(refit.value))
                hypothesis = others[:j] + (candidate.effect(refit.value),) + others[j:]
                refitted.append(_effect_json(candidate, refit.value))
            chosen_fit = Fit(chosen_fit.candidate, chosen[-1][1], chosen[-1][2], chosen[-1][3], chosen_fit.sse)
            clock["fits"] += time.perf_counter() - tick

        tick = time.perf_counter()
        after = _errors(evaluator, sensed + hypothesis)
        clock["validation"] += time.perf_counter() - tick
        step_interval = tuple(_interval_json(chosen_fit.candidate, *chosen_fit.interval))
        steps.append(Step(effect=_effect_json(chosen_fit.candidate, chosen_fit.value),
                          interval=step_interval,  # type: ignore[arg-type]
                          on_bound=chosen_fit.on_bound, before=current, after=after,
                          heldout_gain_z=float(min(z_scores[pick], 1e6)), equivalent_alternatives=alternatives,
                          screened=tuple((s.candidate.label, float(s.reduction)) for s in scores[:8]),
                          refitted=tuple(refitted)))
        current = after
    else:
        if _at_floor(_search_summary(evaluator, hypothesis), search_floor, search_floor_dims, settings,
                     settings.search_margin):
            stop_reason = "held-out error reached the noise floor"

    # Before any noise is added: what the data cannot resolve among the deterministic effects.
    tick = time.perf_counter()
    gauge_notes: list[str] = []
    identified = _identify(evaluator, hypothesis, chosen, settings.seed)
    if identified is not None and identified.unresolved:
        hypothesis, chosen, gauge_notes = _fix_gauge(evaluator, hypothesis, chosen, identified, settings)
        if gauge_notes:
            current = _errors(evaluator, sensed + hypothesis)
            identified = _identify(evaluator, hypothesis, chosen, settings.seed)
    clock["validation"] += time.perf_counter() - tick
    unexplained = not _at_floor(_search_summary(evaluator, hypothesis), search_floor, search_floor_dims, settings,
                                 settings.explained_margin)
    drifting = [] if identified is None else [drift.label for drift in identified.drifts]
    if drifting:
        # However small the residual left, no constant effect explains every episode.
        unexplained = True
        stop_reason += (f"; {', '.join(drifting)} drift{'s' if len(drifting) == 1 else ''} between the earlier and "
                        "the later episodes: no constant effect explains them all")
    tick = time.perf_counter()
    # A residual the state and command predict is a model error: no noise fit may absorb it.
    predictability = residual_predictability(evaluator, sensed + hypothesis, seed=settings.seed) if unexplained else None
    clock["validation"] += time.perf_counter() - tick
    if predictability is not None and predictability.systematic:
        stop_reason += (f"; the rest is systematic (state and command predict {predictability.heldout_r2:.0%} of it "
                        "on held-out episodes), not noise")
    elif unexplained and not drifting and len(chosen) < settings.max_effects:
        # What no deterministic effect explains may still be the spread of a noisy command.
        tick = time.perf_counter()
        noise = estimate_action_noise(evaluator, sensed + hypothesis)
        # The noise must also explain how the error grows over H steps: kicks that are
        # independent from step to step add up far less than a model error that keeps pushing.
        growth = None if noise is None else horizon_under_action_noise(evaluator, sensed + hypothesis, noise.std,
                                                                       seed=settings.seed)
        clock["validation"] += time.perf_counter() - tick
        if noise is not None and growth is not None and not growth.consistent:
            stop_reason += (f"; a command noise of std {noise.std:.3g} would explain the one-step spread, but the "
                            f"{settings.horizon}-step error is {growth.ratio:.1f} times what that noise gives: "
                            "a model error, not noise")
            noise = None
        if noise is not None:
            candidate = Candidate("action_noise", None, 0.0, 0.0, np.inf, 0.0, "smooth")
            chosen.append((candidate, noise.std, noise.interval, False))
            steps.append(Step(effect=_effect_json(candidate, noise.std), interval=noise.interval, on_bound=False,
                              before=current, after=current, heldout_gain_z=0.0, equivalent_alternatives=(),
                              screened=(("action_noise on all", noise.share),), refitted=(), stochastic=True))
            unexplained = False
            stop_reason += f"; the rest is action noise (a command correction explains {noise.share:.0%} of it)"

    chosen = sensed_chosen + chosen
    effects_added = []
    for c, v, (lo, hi), bound in chosen:
        entry = {**_effect_json(c, v), "interval": _interval_json(c, lo, hi), "interval_method": "profile grid"
                 if c.search == "threshold" else ("exact enumeration" if c.search in ("integer", "categorical")
                                                  else "Gauss-Newton (rows independent)"), "on_bound": bound}
        if c.kind == "action_noise":
            entry["interval_method"] = "spread of per-step command corrections"
        elif any(c is s for s, *_ in sensed_chosen):
            entry["interval_method"] = ("read off the stored states (exact)" if c.search == "integer" else
                                        "read off the stored states (95%: 1.96 standard errors across episodes)")
        elif identified is not None and c.label in identified.intervals:
            entry["interval"] = list(identified.intervals[c.label])
            entry["interval_method"] = f"episode bootstrap ({identified.resamples} resamples, linearized)"
        entry["values_during_search"] = history.get(c.label, [])
        entry["effect"] = c.effect(v).to_dict() if c.kind != "action_noise" else {"kind": "action_noise", "std": v}
        effects_added.append(entry)
    clock["total"] = time.perf_counter() - started
    notes = list(evaluator.notes)
    notes.extend(gauge_notes)
    for drift in () if identified is None else identified.drifts:
        notes.append(f"{drift.label} is {drift.earlier:.4g} on the earlier half of the episodes and {drift.later:.4g} "
                     f"on the later half ({drift.z:g} standard errors apart): it changes over the recording (wear, "
                     "warming up) or with what the halves visit; the effects of the vocabulary are constant, so "
                     "the value reported is a compromise the calibrated model cannot improve on")
    if predictability is not None and predictability.systematic:
        notes.append(f"the remaining residual is predictable from state and command (held-out R^2 "
                     f"{predictability.heldout_r2:.2f}): a model error outside what was added, not noise")
    if data.recorded_env_id and data.recorded_env_id != env_id:
        notes.insert(0, f"the dataset names {data.recorded_env_id!r} as its env; diagnosed against {env_id!r}")
    engine_note = engine_gap_note(data.recorded_env_id)  # data from DART: a residual no effect explains
    if engine_note is not None:
        notes.insert(0, engine_note)
    for c, v, _, bound in chosen:
        if bound:
            notes.append(f"{c.label} = {v:.4g} sits on its bound [{c.low:g}, {c.high:g}]: the true value may lie beyond")
    return Diagnosis(
        env_id=env_id, dataset=data.origin or "<in-memory transitions>", transitions=data.size,
        state_source="rebuilt from observations" if evaluator.rebuilt else "stored qpos/qvel",
        notes=tuple(notes), effects_added=tuple(effects_added), error_before=first, error_after=current,
        noise_floor=floor, noise_floor_per_dimension=tuple(float(x) for x in floor_dims),
        unexplained_residual=unexplained,
        stop_reason=stop_reason, steps=tuple(steps),
        calibrated_env=source.calibrated_env([c.effect(v) for c, v, _, _ in chosen]),
        action_channel_share=share_before,
        dimension_names=tuple(source.observation_map.names[i] for i in evaluator.dims),
        timings={k: round(v, 3) for k, v in clock.items()},
        residual_predictability=predictability, identifiability=identified,
        observation_check={"bias_candidates": [source.observation_map.names[d] for d in check.bias_allowed],
                           "delay_candidates": [source.observation_map.names[d] for d in check.delay_allowed],
                           "largest_discrepancy": check.max_discrepancy},
        noise_floor_source=check.floor_source, candidates_searched=len(library),
        search_horizon=settings.search_horizon)


Chosen = tuple[Candidate, float, tuple[float, float], bool]


def _sensor_effects(check: ObservationCheck) -> list[tuple[Candidate, float, tuple[float, float]]]:
    """The observation delays and offsets the stored states show, as candidates at their measured
    values (the delay in whole control steps, the offset with its 95% interval across episodes)."""
    out: list[tuple[Candidate, float, tuple[float, float]]] = []
    for index, steps in sorted(check.delay_steps.items()):
        out.append((Candidate("obs_delay", index, 0, 1, 2, 1, "integer"), float(steps), (float(steps), float(steps))))
    for index, (value, standard_error) in sorted(check.bias_values.items()):
        out.append((Candidate("obs_bias", index, 0.0, -1e3, 1e3, 0.01, "smooth"), value,
                    (value - 1.96 * standard_error, value + 1.96 * standard_error)))
    return out


def _identify(evaluator: ResidualEvaluator, hypothesis: Hypothesis, chosen: list[Chosen],
              seed: int) -> Identifiability | None:
    smooth = [(i, c, v) for i, (c, v, _, _) in enumerate(chosen) if c.search == "smooth"]
    return identifiability(evaluator, hypothesis, smooth, seed=seed)


def _fix_gauge(evaluator: ResidualEvaluator, hypothesis: Hypothesis, chosen: list[Chosen],
               identified: Identifiability, settings: DiagnosisSettings) -> tuple[Hypothesis, list[Chosen], list[str]]:
    """Where the data cannot separate some effects (a near-symmetry, e.g. every mass and every
    force scaled together), hold one of them at the source's value (a mass first: the source's
    total mass is the natural gauge), refit the rest, and keep the gauge if held-out error stays
    within the complexity penalty."""
    notes: list[str] = []
    for direction in identified.unresolved:
        labels = [label for label in direction if any(c.label == label for c, *_ in chosen)]
        if len(labels) < 2:
            continue
        held = max(labels, key=lambda label: (label.startswith("mass"), abs(direction[label])))
        index = next(i for i, (c, *_) in enumerate(chosen) if c.label == held)
        trial_chosen = chosen[:index] + chosen[index + 1:]
        trial = hypothesis[:index] + hypothesis[index + 1:]
        for j, (candidate, value, _, _) in enumerate(trial_chosen):
            others = trial[:j] + trial[j + 1:]
            refit = fit(evaluator, others, candidate, value)
            trial_chosen[j] = (candidate, refit.value, refit.interval, refit.on_bound)
            trial = others[:j] + (candidate.effect(refit.value),) + others[j:]
        before, = evaluator.search_residuals([hypothesis], "heldout")
        after, = evaluator.search_residuals([trial], "heldout")
        if float(np.sum(after**2)) <= (1.0 + settings.min_relative_gain) * float(np.sum(before**2)):
            others = ", ".join(label for label in labels if label != held)
            notes.append(f"gauge: {held} is held at the source's value; the data cannot separate it from {others} "
                         "(they move together along a direction the data do not resolve), so they were refitted "
                         "with it fixed")
            hypothesis, chosen = trial, trial_chosen
    return hypothesis, chosen, notes
