"""The source-target gap of each task: how hard its shift is for a policy trained in the source.

The protocol measures it with ``sac-source`` (RL on source) evaluated on both sides of a task:
``offdyn-bench evaluate --side source`` and the ordinary target evaluation. Per task this gives the
return in the source, the return kept in the target, and, where the task has an oracle at the
records' budget, how far below RL on target it stays: its normalized target score and P(oracle >
RL on source) over training seeds. The core suite asks RL on source to clearly fail in the target
(PROTOCOL.md §7); these numbers are that test at a protocol budget.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from typing import Any, Literal

import numpy as np

from offdyn_bench.protocol.definition import ProtocolError
from offdyn_bench.protocol.scoring import group_seed_means, single_budget

SIDES = ("source", "target")


@dataclasses.dataclass(frozen=True)
class TaskGap:
    method: str
    task: str
    budget: str
    source_seed_means: tuple[float, ...]
    """Per training seed, the mean return in the source (empty when no source-side record was given)."""
    target_seed_means: tuple[float, ...]
    random_return: float | None
    oracle_seed_means: tuple[float, ...] | None
    """The task's oracle at ``budget`` per training seed; None where there is none."""
    oracle_from: str | None = None
    """``reference file`` (the protocol's recorded oracle) or ``records`` (the ``sac-target`` records
    given beside the method's, for a task the reference file has no oracle for); None: no oracle."""
    zero_command_return: float | None = None
    """The task's zero-command reference (the policy that commands nothing); None where none is recorded."""

    @property
    def source_return(self) -> float | None:
        return float(np.mean(self.source_seed_means)) if self.source_seed_means else None

    @property
    def target_return(self) -> float | None:
        return float(np.mean(self.target_seed_means)) if self.target_seed_means else None

    @property
    def oracle_return(self) -> float | None:
        return float(np.mean(self.oracle_seed_means)) if self.oracle_seed_means else None

    @property
    def kept(self) -> float | None:
        """Target return over source return; None unless both exist and the source return is positive
        (a fraction of a negative return means nothing)."""
        source, target = self.source_return, self.target_return
        if source is None or target is None or source <= 0:
            return None
        return target / source

    @property
    def normalized_target(self) -> float | None:
        """The target return as a protocol score, 100 x (J - J_random) / (J_oracle - J_random)."""
        target, oracle = self.target_return, self.oracle_return
        if target is None or oracle is None or self.random_return is None or oracle == self.random_return:
            return None
        return 100.0 * (target - self.random_return) / (oracle - self.random_return)

    @property
    def oracle_better_probability(self) -> float | None:
        """P(oracle seed > this method's seed) in the target, the protocol's Mann-Whitney statistic."""
        if not self.oracle_seed_means or not self.target_seed_means:
            return None
        from offdyn_bench.protocol.statistics import probability_of_improvement

        oracle = np.asarray(self.oracle_seed_means)[:, None]
        return probability_of_improvement(oracle, np.asarray(self.target_seed_means)[:, None])

    def to_dict(self) -> dict[str, Any]:
        return {"method": self.method, "task": self.task, "budget": self.budget,
                "source_return": self.source_return, "source_seeds": len(self.source_seed_means),
                "target_return": self.target_return, "target_seeds": len(self.target_seed_means),
                "kept": self.kept, "random_return": self.random_return, "oracle_return": self.oracle_return,
                "oracle_seeds": len(self.oracle_seed_means or ()), "oracle_from": self.oracle_from,
                "zero_command_return": self.zero_command_return,
                "normalized_target": self.normalized_target,
                "p_oracle_better": self.oracle_better_probability}


ORACLE_METHOD = "sac-target"
RL_ON_SOURCE = "sac-source"


def measure_gaps(records: Sequence[Mapping[str, Any]], reference_file: str | None = None) -> list[TaskGap]:
    """One row per (method, task) of ``records`` (evaluation.json contents, either side, one budget),
    with the task's references at that budget from the reference file; in task order.

    ``sac-target`` target-side records among them are the oracle of a task the reference file has
    no oracle for (a candidate task, or oracle runs not recorded yet), not rows of their own; where
    the reference file has one, it is the protocol's and the records are not used."""
    from offdyn_bench.protocol.references import reference_scores

    if not records:
        raise ProtocolError("no evaluations given; pass sac-source's evaluation.json files, target side and "
                            "source side (offdyn-bench evaluate --side source)")
    def key_of(record: Mapping[str, Any], where: str) -> tuple[str, str, str]:
        side = record.get("side", "target")
        if side not in SIDES:
            raise ProtocolError(f"{where}: side {side!r}; expected one of {', '.join(SIDES)}")
        return str(record.get("method") or "agent"), str(record["task"]), str(side)

    seeds = group_seed_means(records, key_of, lambda key: f"of task {key[1]!r} ({key[2]} side)")
    budget = single_budget(records, "measure")
    references = reference_scores(reference_file)
    given_oracle = {task: tuple(means[s] for s in sorted(means))
                    for (method, task, side), means in seeds.items() if method == ORACLE_METHOD and side == "target"}
    rows = {(m, t) for m, t, side in seeds if not (m == ORACLE_METHOD and side == "target"
                                                 and (m, t, "source") not in seeds)}
    if not rows:
        raise ProtocolError(f"only {ORACLE_METHOD} target-side records given; pass the method's records beside them "
                            "(sac-source's on both sides for the source-target gap)")
    gaps = []
    for method, task in sorted(rows, key=lambda mt: (mt[1], mt[0])):
        source = seeds.get((method, task, "source"), {})
        target = seeds.get((method, task, "target"), {})
        if source and target and set(source) != set(target):
            raise ProtocolError(f"{method} on {task}: the source side has training seeds {sorted(source)}, the "
                                f"target side {sorted(target)}; evaluate the same policies on both sides")
        task_references = references.get(task, {})
        random, zero = task_references.get("random"), task_references.get("zero-command")
        oracle = task_references.get(f"oracle/{budget}")
        oracle_means, oracle_from = ((oracle.seed_means(), "reference file") if oracle is not None else
                                     (given_oracle[task], "records") if task in given_oracle else (None, None))
        gaps.append(TaskGap(method, task, budget,
                            tuple(source[s] for s in sorted(source)), tuple(target[s] for s in sorted(target)),
                            random.mean_return if random is not None else None, oracle_means, oracle_from,
                            zero.mean_return if zero is not None else None))
    return gaps


def _number(value: float | None, form: str = "{:.1f}") -> str:
    return "-" if value is None else form.format(value)


def _oracle_cell(gap: TaskGap) -> str:
    # Its seed count too: an oracle from records given may have fewer seeds than a recorded one.
    if gap.oracle_seed_means is None:
        return "-"
    mark = "*" if gap.oracle_from == "records" else ""
    return f"{_number(gap.oracle_return)}{mark} ({len(gap.oracle_seed_means)})"


def gaps_markdown(gaps: Sequence[TaskGap]) -> str:
    """A table: per (method, task) the returns on both sides, the fraction kept, and the oracle."""
    budget = gaps[0].budget if gaps else "-"
    lines = [f"| task | method | source return | target return | kept | oracle/{budget} | "
             "normalized target score | P(oracle > method) |",
             "|---|---|---:|---:|---:|---:|---:|---:|"]
    for gap in gaps:
        lines.append(
            f"| {gap.task} | {gap.method} | {_number(gap.source_return)} ({len(gap.source_seed_means)}) | "
            f"{_number(gap.target_return)} ({len(gap.target_seed_means)}) | {_number(gap.kept, '{:.2f}')} | "
            f"{_oracle_cell(gap)} | "
            f"{_number(gap.normalized_target)} | "
            f"{_number(gap.oracle_better_probability, '{:.2f}')} |")
    lines += ["", "Returns (the oracle's too) are means over training seeds (their number in brackets), each "
                  "seed's return the mean of its episodes. kept = target / source return (only for a positive "
                  "source return). The normalized score and P(oracle > method) need the task's random and oracle "
                  "references at this budget; '-' where they are missing."]
    if any(gap.oracle_from == "records" for gap in gaps):
        lines.append("* an oracle from the sac-target records given, for a task the reference file has none "
                     "for (not a recorded reference).")
    return "\n".join(lines) + "\n"


AdmissionVerdict = Literal["passes", "fails", "undecided"]


@dataclasses.dataclass(frozen=True)
class Admission:
    """A pair against the core suite's same-budget test (PROTOCOL.md §9, decision 1): does its
    oracle beat the policy that commands nothing, and RL on source, in the target, the second with
    P(oracle > RL on source) >= the threshold over at least ``MIN_SEEDS`` training seeds on each side
    and RL on source's normalized target score at most the bound (well below the oracle)?"""

    task: str
    budget: str
    rl_on_source_seeds: int
    oracle_seeds: int
    probability: float | None
    verdict: AdmissionVerdict
    reason: str
    in_core_suite: bool
    """Whether the pair is in the current protocol version's core suite."""
    rl_on_source_score: float | None = None
    """RL on source's normalized target score against this oracle; None without a random reference or oracle."""
    missing_oracle_mean_needed: float | None = None
    """For a pair undecided only for want of oracle seeds: the mean return its missing oracle seeds
    must exceed for conditions (a) and (c) to hold (P aside); None otherwise."""

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


def best_reachable_probability(probability: float, oracle_seeds: int, rl_on_source_seeds: int,
                               seeds_needed: int) -> float:
    """The largest P(oracle > RL on source) that completing both sides to ``seeds_needed`` seeds can
    give, from ``probability`` over the seeds given: every missing oracle seed beats every
    RL-on-source seed and every missing RL-on-source seed loses to every oracle seed. Below the
    admission threshold, the pair fails whatever the missing seeds score. ``probability`` is the
    Mann-Whitney statistic (ties count 1/2), so the wins it stands for are a multiple of 1/2."""
    if oracle_seeds < 1 or rl_on_source_seeds < 1:
        raise ProtocolError(f"a probability needs a seed on each side; got {oracle_seeds} oracle and "
                            f"{rl_on_source_seeds} RL-on-source seed(s)")
    missing_oracle = max(0, seeds_needed - oracle_seeds)
    missing_source = max(0, seeds_needed - rl_on_source_seeds)
    # Back to a count of half-wins first, so that float rounding cannot move a bound that is exactly
    # the threshold below it.
    wins_given = round(probability * oracle_seeds * rl_on_source_seeds * 2) / 2
    wins = (wins_given
            + missing_oracle * (rl_on_source_seeds + missing_source) + oracle_seeds * missing_source)
    return wins / ((oracle_seeds + missing_oracle) * (rl_on_source_seeds + missing_source))


def missing_oracle_mean_needed(gap: TaskGap, seeds_needed: int) -> float | None:
    """The mean return that the oracle seeds ``gap`` lacks (up to ``seeds_needed``) must exceed for
    the oracle's mean to beat the zero command (condition a) and for RL on source to score at most
    the bound (condition c): a pair with two oracle seeds of 250 that needs its three missing ones
    to average 500 is, in practice, decided. None where it is not computable: no oracle seed
    missing, RL-on-source seeds missing too (their mean would move), or no zero-command or random
    reference."""
    from offdyn_bench.protocol.definition import ADMISSION_MAX_SOURCE_SCORE

    given = list(gap.oracle_seed_means or ())
    missing = seeds_needed - len(given)
    if (not given or missing <= 0 or len(gap.target_seed_means) < seeds_needed
            or gap.zero_command_return is None or gap.random_return is None or gap.target_return is None):
        return None
    random = gap.random_return
    # (c): 100 (J - r) / (O - r) <= bound, with O > r, is O >= r + 100 (J - r) / bound; at J <= r any O > r.
    least_for_score = random + max(0.0, 100.0 * (gap.target_return - random) / ADMISSION_MAX_SOURCE_SCORE)
    least_mean = max(gap.zero_command_return, least_for_score)
    return (least_mean * seeds_needed - sum(given)) / missing


def admit(gap: TaskGap) -> Admission:
    """The test on one measured gap of RL on source. Too few seeds on either side, no oracle at the
    gap's budget, or no zero-command or random reference, is ``undecided`` (never a pass): the test is
    only as good as its evidence, except that too few seeds whose P could not reach the threshold
    whatever the missing seeds score (:func:`best_reachable_probability`) already fail. An oracle
    whose mean return does not exceed the zero command's fails whatever RL on source does: on its
    normalized scale, doing nothing would score above 100. RL on source that the oracle beats
    reliably (P) but only by a little (normalized score above the bound) fails too: it does not
    clearly fail in the target."""
    from offdyn_bench.protocol.definition import (
        ADMISSION_MAX_SOURCE_SCORE,
        ADMISSION_PROBABILITY,
        CORE_SUITE,
        MIN_SEEDS,
    )
    from offdyn_bench.protocol.references import normalize

    if gap.method != RL_ON_SOURCE:
        raise ProtocolError(f"the admission test compares the oracle with RL on source ({RL_ON_SOURCE}); "
                            f"got records of {gap.method!r} on {gap.task}: pass {RL_ON_SOURCE}'s target-side "
                            f"records (and {ORACLE_METHOD}'s for a task without a recorded oracle)")
    oracle_seeds = len(gap.oracle_seed_means or ())
    seeds = len(gap.target_seed_means)
    probability = gap.oracle_better_probability
    needed: float | None = None  # what missing oracle seeds must average; only for a pair short of them
    if gap.oracle_seed_means is None:
        verdict, reason = "undecided", (f"no {gap.budget} oracle: record one (protocol reference oracle) or pass "
                                        f"{ORACLE_METHOD}'s records")
    elif min(seeds, oracle_seeds) < MIN_SEEDS:
        short = [f"{n} {who} seed{'s' if n != 1 else ''}" for who, n in (("RL-on-source", seeds),
                                                                          ("oracle", oracle_seeds)) if n < MIN_SEEDS]
        reachable = (None if probability is None else
                     best_reachable_probability(probability, oracle_seeds, seeds, MIN_SEEDS))
        if reachable is not None and reachable < ADMISSION_PROBABILITY:
            # The seeds given already decide it: no result of the missing ones lifts P to the threshold.
            verdict, reason = "fails", (f"P = {probability:.2f} on {' and '.join(short)}; even if every missing "
                                        f"seed went the oracle's way, P would reach at most {reachable:.2f} < "
                                        f"{ADMISSION_PROBABILITY:.2f} with {MIN_SEEDS} on each side")
        else:
            verdict, reason = "undecided", f"{' and '.join(short)}; the test needs {MIN_SEEDS} on each side"
            needed = missing_oracle_mean_needed(gap, MIN_SEEDS)  # None without an oracle seed
            if needed is not None:
                given_mean = float(np.mean(gap.oracle_seed_means))  # type: ignore[arg-type]  # seeds exist here
                # Said where the missing seeds must do better than the seeds given: that decides a run.
                if needed > given_mean:
                    missing = MIN_SEEDS - oracle_seeds
                    reason += (f"; to pass, the {missing} missing oracle seed{'s' if missing != 1 else ''} must "
                               f"average above {needed:.1f} (the {oracle_seeds} given: {given_mean:.1f})")
    elif gap.zero_command_return is None:
        verdict, reason = "undecided", (f"no zero-command reference: record one (offdyn-bench protocol reference "
                                        f"zero-command --task {gap.task})")
    elif not gap.oracle_return > gap.zero_command_return:  # type: ignore[operator]  # oracle present here
        doing_nothing = (None if gap.random_return is None or gap.oracle_return == gap.random_return else
                         float(normalize(np.float64(gap.zero_command_return), gap.random_return, gap.oracle_return)))
        verdict, reason = "fails", (f"the oracle ({gap.oracle_return:.1f}) does not beat the zero command "
                                    f"({gap.zero_command_return:.1f})"
                                    + (f": doing nothing would score {doing_nothing:.0f} normalized"
                                       if doing_nothing is not None else ""))
    elif probability is None or probability < ADMISSION_PROBABILITY:
        verdict, reason = "fails", f"P = {_number(probability, '{:.2f}')} < {ADMISSION_PROBABILITY:.2f}"
    elif gap.normalized_target is None:
        verdict, reason = "undecided", (f"no random reference, so no normalized score: record one (offdyn-bench "
                                        f"protocol reference random --task {gap.task})")
    elif gap.normalized_target > ADMISSION_MAX_SOURCE_SCORE:
        verdict, reason = "fails", (f"RL on source scores {gap.normalized_target:.1f} normalized, above "
                                    f"{ADMISSION_MAX_SOURCE_SCORE:.0f}: not well below the oracle "
                                    f"(P = {probability:.2f})")
    else:
        verdict, reason = "passes", (f"P = {probability:.2f} >= {ADMISSION_PROBABILITY:.2f}; RL on source scores "
                                     f"{gap.normalized_target:.1f} <= {ADMISSION_MAX_SOURCE_SCORE:.0f} normalized")
    return Admission(gap.task, gap.budget, seeds, oracle_seeds, probability, verdict, reason,
                     gap.task in CORE_SUITE, gap.normalized_target, needed)


def admissions_markdown(admissions: Sequence[Admission]) -> str:
    from offdyn_bench.protocol.definition import PROTOCOL_VERSION

    budget = admissions[0].budget if admissions else "-"
    lines = [f"| task | in core suite {PROTOCOL_VERSION} | RL-on-source seeds | oracle/{budget} seeds | "
             "P(oracle > RL on source) | RL on source, normalized | verdict |",
             "|---|---|---:|---:|---:|---:|---|"]
    for one in admissions:
        lines.append(f"| {one.task} | {'yes' if one.in_core_suite else 'no'} | {one.rl_on_source_seeds} | "
                     f"{one.oracle_seeds} | {_number(one.probability, '{:.2f}')} | "
                     f"{_number(one.rl_on_source_score)} | {one.verdict}: {one.reason} |")
    core = [one for one in admissions if one.in_core_suite]
    counts = ", ".join(f"{sum(one.verdict == v for one in core)} {v}" for v in ("passes", "fails", "undecided"))
    coverage = admission_coverage(admissions)
    lines += ["", f"Core-suite pairs given: {len(core)} ({counts}). The test: PROTOCOL.md §9, decision 1.",
              coverage.sentence()]
    return "\n".join(lines) + "\n"


@dataclasses.dataclass(frozen=True)
class Coverage:
    """Which of the robots and shift families the core suite must cover have a pair that passes."""

    passing: tuple[str, ...]
    robots: Mapping[str, tuple[str, ...]]
    """Robot -> its passing pairs (empty: none passes), for every robot of the current core suite."""
    shifts: Mapping[str, tuple[str, ...]]
    """Shift family -> its passing pairs, for every shift family of the current core suite."""

    @property
    def uncovered(self) -> tuple[str, ...]:
        return tuple([r for r, pairs in self.robots.items() if not pairs]
                     + [s for s, pairs in self.shifts.items() if not pairs])

    def sentence(self) -> str:
        def listed(groups: Mapping[str, tuple[str, ...]], covered: bool) -> str:
            names = [name for name, pairs in groups.items() if bool(pairs) == covered]
            return ", ".join(names) if names else "none"

        return (f"Passing pairs: {len(self.passing)}; robots covered: {listed(self.robots, True)}, without a "
                f"passing pair: {listed(self.robots, False)}; shift families covered: {listed(self.shifts, True)}, "
                f"without one: {listed(self.shifts, False)}.")

    def to_dict(self) -> dict[str, Any]:
        return {"passing": list(self.passing), "robots": {k: list(v) for k, v in self.robots.items()},
                "shifts": {k: list(v) for k, v in self.shifts.items()}, "uncovered": list(self.uncovered)}


def admission_coverage(admissions: Sequence[Admission]) -> Coverage:
    """What a core suite made of the passing pairs would cover: every robot and shift family of the
    current core suite (what the suite promises), each with the pairs given that pass for it."""
    from offdyn_bench.protocol.definition import CORE_SUITE
    from offdyn_bench.tasks import get_task

    passing = tuple(one.task for one in admissions if one.verdict == "passes")
    core = [get_task(task) for task in CORE_SUITE]
    robots = {robot: tuple(t for t in passing if get_task(t).robot == robot)
              for robot in sorted({pair.robot for pair in core})}
    shifts = {shift: tuple(t for t in passing if get_task(t).shift == shift)
              for shift in sorted({pair.shift for pair in core})}
    return Coverage(passing, robots, shifts)
