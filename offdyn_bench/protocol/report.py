"""A score report over evaluation records: what `offdyn-bench protocol score` and the demo print."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from typing import Any

from offdyn_bench.protocol.definition import ProtocolError
from offdyn_bench.protocol.scoring import MethodScores, method_scores

BOOTSTRAP_REPS = 2000
BOOTSTRAP_SEED = 0


@dataclasses.dataclass(frozen=True)
class ScoreReport:
    budget: str | None
    tasks: tuple[str, ...]
    methods: tuple[MethodScores, ...]
    aggregates: Mapping[str, Mapping[str, Any]]
    """method -> {"iqm": Interval, ...}; empty when a task lacks references."""
    improvement: Mapping[str, Any]
    """"A>B" -> Interval of P(A > B); empty without normalized scores."""
    note: str

    def to_dict(self) -> dict[str, Any]:
        return {
            "budget": self.budget, "tasks": list(self.tasks), "note": self.note,
            "methods": {m.method: {"seeds": list(m.seeds),
                                   "raw_mean_return": {t: float(m.raw[:, j].mean()) for j, t in enumerate(m.tasks)},
                                   "raw_per_seed": m.raw.tolist(),
                                   "normalized_per_seed": None if m.normalized is None else m.normalized.tolist()}
                        for m in self.methods},
            "aggregates": {m: {k: dataclasses.asdict(v) for k, v in stats.items()}
                           for m, stats in self.aggregates.items()},
            "probability_of_improvement": {k: dataclasses.asdict(v) for k, v in self.improvement.items()},
        }

    def to_text(self) -> str:
        lines = []
        width = max(len(t) for t in self.tasks)
        header = f"{'task':{width}s}  " + "  ".join(f"{m.method:>22s}" for m in self.methods)
        lines += ["mean target return (normalized score) per task, over training seeds:", header]
        for j, task in enumerate(self.tasks):
            cells = []
            for m in self.methods:
                cell = f"{m.raw[:, j].mean():.1f}"
                if m.normalized is not None:
                    cell += f" ({m.normalized[:, j].mean():.1f})"
                cells.append(f"{cell:>22s}")
            lines.append(f"{task:{width}s}  " + "  ".join(cells))
        if self.aggregates:
            lines.append("aggregate normalized score, 95% stratified-bootstrap intervals:")
            for method, stats in self.aggregates.items():
                iqm, gap = stats["iqm"], stats["optimality_gap"]
                lines.append(f"  {method}: IQM {iqm.point:.1f} [{iqm.low:.1f}, {iqm.high:.1f}], optimality gap "
                             f"{gap.point:.1f} [{gap.low:.1f}, {gap.high:.1f}]")
            for pair, interval in self.improvement.items():
                first, second = pair.split(">")
                if first > second:  # P(B > A) = 1 - P(A > B): print each pair once
                    continue
                lines.append(f"  P({pair.replace('>', ' > ')}) = {interval.point:.2f} "
                             f"[{interval.low:.2f}, {interval.high:.2f}]")
        lines.append(self.note)
        return "\n".join(lines)


def score_report(records: Sequence[Mapping[str, Any]], budget: str | None = None,
                 references: Mapping[str, tuple[float, float]] | None = None) -> ScoreReport:
    """Group ``records`` by method; every method must cover the same tasks."""
    from offdyn_bench.protocol.statistics import aggregate, probability_of_improvement_ci

    if not records:
        raise ProtocolError("no evaluations to score")
    budgets = {r.get("budget") for r in records}
    if budget is None:
        if len(budgets) > 1:
            raise ProtocolError(f"the evaluations mix budgets {sorted(map(str, budgets))}; pick one with --budget")
        budget = next(iter(budgets))
    grouped: dict[str, list[Mapping[str, Any]]] = {}
    for record in records:
        grouped.setdefault(str(record.get("method") or "agent"), []).append(record)
    task_sets = {method: sorted({r["task"] for r in rs}) for method, rs in grouped.items()}
    tasks = tuple(next(iter(task_sets.values())))
    if any(tuple(t) != tasks for t in task_sets.values()):
        raise ProtocolError("methods cover different tasks: " + "; ".join(f"{m}: {', '.join(t)}"
                                                                          for m, t in task_sets.items()))
    methods = tuple(method_scores(m, rs, budget, tasks, references=references) for m, rs in sorted(grouped.items()))
    missing = sorted({t for m in methods for t in m.missing_references})
    aggregates: dict[str, Any] = {}
    improvement: dict[str, Any] = {}
    if missing:
        where = "the references given" if references is not None else (
            f"budget {budget!r}" if budget else "no protocol budget")
        note = (f"normalized scores need random and oracle references; missing for {', '.join(missing)} at {where}: "
                "raw returns only")
    else:
        matrices = {m.method: m.normalized for m in methods}
        aggregates = aggregate(matrices, reps=BOOTSTRAP_REPS, seed=BOOTSTRAP_SEED)
        for a in methods:
            for b in methods:
                if a.method != b.method:
                    improvement[f"{a.method}>{b.method}"] = probability_of_improvement_ci(
                        a.normalized, b.normalized, reps=BOOTSTRAP_REPS, seed=BOOTSTRAP_SEED)
        n_seeds = sorted({len(m.seeds) for m in methods})
        note = (f"{len(tasks)} task(s), {'/'.join(map(str, n_seeds))} training seed(s) per method; "
                f"normalized = 100 x (J - J_random) / (J_oracle - J_random)")
    return ScoreReport(budget, tasks, methods, aggregates, improvement, note)
