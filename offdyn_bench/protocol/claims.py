"""The papers' headline claims, checked task by task on evaluation records.

Two papers make claims the suite's reference results can test:

* DAP (Section 5.2): DAP at least doubles the target return of RL on source (``sac-source``) on
  every task, and DAP+U improves on DAP;
* H2O (Table 1): H2O beats DARC and CQL on the HalfCheetah gravity, friction and joint-noise
  settings (a shifted simulator as the source, the nominal robot as the real system), for each of
  the medium, medium-replay and medium-expert datasets.

A claim is checked where both of its methods were evaluated. Methods are compared on the same task
and the same target dataset; a method that trains on no target data (``sac-source``,
``sac-target``) joins every dataset of its task. The verdict uses each method's mean target return
over its training seeds (each seed's return the mean of its protocol episodes), as the papers
state their claims; beside it, P(A > B) over training seeds (the Mann-Whitney statistic the
protocol's aggregate uses) says how clearly the seeds separate. "At least doubles" is a ratio of
raw returns, as the DAP paper reports them, so it is defined only where RL on source's mean
return is positive; elsewhere the row says so instead of giving a verdict.

A row also carries what its methods' trainings were too short for (``train``'s budget warnings,
recomputed from each record's train command: its ``--set`` settings on this version's defaults,
and its steps). DARC's published schedule starts its reward correction at step 100,000, the whole
``lite`` budget, so at ``lite`` its runs train SAC on the source alone: a verdict against them is
not one against DARC's correction, and the row says so.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from offdyn_bench.errors import OffdynError
from offdyn_bench.protocol.definition import ProtocolError
from offdyn_bench.protocol.scoring import group_seed_means, single_budget

NO_DATASET = "-"
"""The dataset label of a method that trains on no target data."""


@dataclasses.dataclass(frozen=True)
class PaperClaim:
    """``better`` reaches at least ``factor`` times ``worse``'s return (``factor`` 1: beats it)."""

    name: str
    better: str
    worse: str
    factor: float
    paper: str
    scope: str
    """Where the paper makes the claim: ``every task`` or ``h2o-halfcheetah``."""

    def claimed_on(self, task: str) -> bool:
        if self.scope == "every task":
            return True
        from offdyn_bench.datasets.recipes import is_h2o_setting
        from offdyn_bench.tasks import get_task

        pair = get_task(task)
        return pair.robot == "HalfCheetah" and is_h2o_setting(pair)

    def verdict(self, better: float, worse: float) -> bool | None:
        """Whether the claim holds for these returns; None where a ratio of returns is undefined."""
        if self.factor == 1.0:
            return better > worse
        if worse <= 0:
            return None
        return better >= self.factor * worse


PAPER_CLAIMS: tuple[PaperClaim, ...] = (
    PaperClaim("dap >= 2x rl-on-source", "dap", "sac-source", 2.0, "DAP, Section 5.2", "every task"),
    PaperClaim("dap-u > dap", "dap-u", "dap", 1.0, "DAP, Section 5.2", "every task"),
    PaperClaim("h2o > darc", "h2o", "darc", 1.0, "H2O, Table 1", "h2o-halfcheetah"),
    PaperClaim("h2o > cql", "h2o", "cql", 1.0, "H2O, Table 1", "h2o-halfcheetah"),
)


@dataclasses.dataclass(frozen=True)
class ClaimCheck:
    claim: PaperClaim
    task: str
    dataset: str
    better_return: float
    worse_return: float
    better_seeds: int
    worse_seeds: int
    holds: bool | None
    probability_of_improvement: float
    claimed_on_task: bool
    caveats: tuple[str, ...] = ()
    """What either method's trainings were too short for (``darc: ...``), from :func:`training_caveats`."""

    @property
    def verdict_text(self) -> str:
        """``holds``, ``does not hold``, or why there is no verdict."""
        if self.holds is None:
            return f"undefined ({self.claim.worse} return <= 0)"
        return "holds" if self.holds else "does not hold"

    def to_dict(self) -> dict[str, Any]:
        return {"claim": self.claim.name, "paper": self.claim.paper, "task": self.task, "dataset": self.dataset,
                "claimed_on_task": self.claimed_on_task, self.claim.better: self.better_return,
                self.claim.worse: self.worse_return, "seeds": {self.claim.better: self.better_seeds,
                                                               self.claim.worse: self.worse_seeds},
                "holds": self.holds, "probability_of_improvement": self.probability_of_improvement,
                "caveats": list(self.caveats)}


def training_caveats(record: Mapping[str, Any]) -> tuple[str, ...]:
    """What the training behind ``record`` was too short for: ``train``'s budget warnings (no
    update before ``random_steps``, no reward correction before ``warmup_steps``, ...), recomputed
    from the record's train command (its ``--set`` settings on this version's defaults) and steps,
    each up to its advice. Empty for a method this version does not know, or a record without a
    readable train command."""
    from baselines.algorithms import ALGORITHMS, apply_overrides
    from baselines.train import budget_warnings
    from offdyn_bench.evaluate import train_command_settings

    method, command, steps = record.get("method"), record.get("train_command"), record.get("steps")
    if method not in ALGORITHMS or not isinstance(command, str) or not isinstance(steps, int):
        return ()
    settings = train_command_settings(command)
    if settings is None:
        return ()
    try:
        config = apply_overrides(ALGORITHMS[str(method)].default_config(), settings, str(method))
    except OffdynError:  # a setting this version does not have: nothing to recompute from
        return ()
    return tuple(warning.split("; ")[0] for warning in budget_warnings(str(method), config, steps))


def dataset_label(record: Mapping[str, Any]) -> str:
    """The target dataset a record's method trained on (its id, or its spec), or :data:`NO_DATASET`."""
    provenance = record.get("dataset")
    if not isinstance(provenance, Mapping) or not provenance:
        return NO_DATASET
    return str(provenance.get("dataset_id") or provenance.get("spec") or NO_DATASET)


def _seed_returns(records: Sequence[Mapping[str, Any]]) -> dict[tuple[str, str, str], dict[int, float]]:
    """(method, task, dataset) -> training seed -> mean target return; a seed twice is refused."""
    def key_of(record: Mapping[str, Any], where: str) -> tuple[str, str, str]:
        if record.get("side", "target") != "target":
            raise ProtocolError(f"{record.get('method')} on {record.get('task')}: a source-side evaluation; the "
                                "claims are about target returns")
        return str(record.get("method") or "agent"), str(record["task"]), dataset_label(record)

    return group_seed_means(records, key_of, lambda key: f"of task {key[1]!r} (dataset {key[2]})")


def check_claims(records: Sequence[Mapping[str, Any]],
                 claims: Sequence[PaperClaim] = PAPER_CLAIMS) -> list[ClaimCheck]:
    """Every claim on every (task, dataset) where both of its methods were evaluated, in task order."""
    from offdyn_bench.protocol.statistics import probability_of_improvement

    if not records:
        raise ProtocolError("no evaluations to check the claims on")
    returns = _seed_returns(records)
    single_budget(records, "check")
    caveats: dict[tuple[str, str, str], dict[str, None]] = {}  # (method, task, dataset) -> caveats, in order
    for record in records:
        key = (str(record.get("method") or "agent"), str(record["task"]), dataset_label(record))
        caveats.setdefault(key, {}).update(dict.fromkeys(training_caveats(record)))
    checks = []
    for task in sorted({task for _, task, _ in returns}):
        datasets = sorted({d for _, t, d in returns if t == task and d != NO_DATASET}) or [NO_DATASET]
        for dataset in datasets:
            for claim in claims:
                sides, side_caveats = [], []
                for method in (claim.better, claim.worse):
                    key = (method, task, dataset) if (method, task, dataset) in returns else (method, task, NO_DATASET)
                    sides.append(returns.get(key))
                    side_caveats += [f"{method}: {caveat}" for caveat in caveats.get(key, {})]
                if sides[0] is None or sides[1] is None:
                    continue
                better = np.array(list(sides[0].values()))
                worse = np.array(list(sides[1].values()))
                checks.append(ClaimCheck(
                    claim, task, dataset, float(better.mean()), float(worse.mean()), better.size, worse.size,
                    claim.verdict(float(better.mean()), float(worse.mean())),
                    probability_of_improvement(better[:, None], worse[:, None]), claim.claimed_on(task),
                    tuple(side_caveats)))
    return checks


def _seeds(n: int) -> str:
    return f"{n} seed" + ("" if n == 1 else "s")


def claims_markdown(checks: Sequence[ClaimCheck]) -> str:
    """One table per claim (task, dataset, both returns, the verdict, P(A > B)), then a tally."""
    if not checks:
        return ("No claim could be checked: each needs both of its methods evaluated on one task "
                "(" + "; ".join(f"{c.name}: {c.better} and {c.worse}" for c in PAPER_CLAIMS) + ").")
    lines: list[str] = []
    for claim in dict.fromkeys(c.claim for c in checks):
        rows = [c for c in checks if c.claim == claim]
        lines += [f"### {claim.name} ({claim.paper})", "",
                  f"| task | dataset | {claim.better} | {claim.worse} | verdict | P({claim.better} > {claim.worse}) |",
                  "|---|---|---:|---:|---|---:|"]
        for c in rows:
            where = "" if c.claimed_on_task else " (not claimed here)"
            lines.append(f"| {c.task}{where} | {c.dataset} | {c.better_return:.1f} ({_seeds(c.better_seeds)}) | "
                         f"{c.worse_return:.1f} ({_seeds(c.worse_seeds)}) | {c.verdict_text} | "
                         f"{c.probability_of_improvement:.2f} |")
        claimed = [c for c in rows if c.claimed_on_task and c.holds is not None]
        lines += ["", f"Where the paper claims it: holds on {sum(bool(c.holds) for c in claimed)} of "
                      f"{len(claimed)} (task, dataset) rows with a verdict.", ""]
        caveated = [c for c in rows if c.caveats]
        if caveated:
            lines += [("What the trainings behind these rows were too short for (the verdict is not about "
                       "what they never ran):"), ""]
            lines += [f"- {c.task}, {c.dataset}: {'; '.join(c.caveats)}" for c in caveated]
            lines.append("")
    return "\n".join(lines).rstrip() + "\n"
