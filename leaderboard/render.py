"""``leaderboard.md`` and a self-contained ``index.html`` from a scored board.

Deterministic: the same store gives the same bytes. Everything is sorted, no date is written, and
the plots are PNGs from matplotlib's Agg backend with its metadata cleared (Agg rasterizes the same
figure to the same pixels).
"""

from __future__ import annotations

import base64
import html
import io
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from leaderboard.reference_runs import ReferenceProgress
from leaderboard.scores import Board, Entry, Interval, Normalization, performance_profile
from leaderboard.store import write_file_atomic
from offdyn_bench.errors import OffdynError

if TYPE_CHECKING:  # annotations only: the claims module is imported where claims are checked
    from offdyn_bench.protocol.claims import ClaimCheck


def _number(value: float, digits: int = 1) -> str:
    return f"{value:.{digits}f}"


def _interval_text(interval: Interval | None) -> str:
    if interval is None:
        return "n/a"
    return f"{interval.point:.1f} [{interval.low:.1f}, {interval.high:.1f}]"


def _method_label(entry: Entry) -> str:
    return f"{entry.submission.method} (reference)" if entry.is_reference else entry.submission.method


def _markdown_cell(text: str) -> str:
    return text.replace("\\", "\\\\").replace("|", "\\|").replace("\n", " ")


def _normalization_notes(board: Board) -> list[str]:
    notes = []
    for budget, normalization in sorted(board.normalizations.items()):
        if normalization.scored_tasks:
            notes.append(f"Normalized scores, budget `{budget}`: over {len(normalization.scored_tasks)} of "
                         f"{len(board.tasks)} core tasks ({', '.join(normalization.scored_tasks)}).")
        else:
            notes.append(f"Normalized scores, budget `{budget}`: none yet; no core task has both a random and "
                         "an oracle reference at this budget.")
        for task, reason in sorted(normalization.excluded.items()):
            notes.append(f"Excluded from the `{budget}` normalized scores: `{task}`: {reason}")
        notes.extend(f"Oracle below the zero command, budget `{budget}`: `{task}`: {text}"
                     for task, text in _below_zero_command(normalization))
    return notes


def _below_zero_command(normalization: Normalization) -> list[tuple[str, str]]:
    """(task, what its flag says) for the scored tasks whose oracle the zero command beats."""
    out = []
    for task, (zero, zero_normalized) in sorted(normalization.below_zero_command.items()):
        j_oracle = normalization.references[task][1]
        out.append((task, f"the policy that commands nothing earns {zero:.1f}, the oracle {j_oracle:.1f}, so doing "
                          f"nothing scores {zero_normalized:.0f} normalized; its scores count in this protocol "
                          "version's aggregates, but measure little (PROTOCOL.md §9, decision 1)."))
    return out


_PROGRESS_TITLE = "Reference runs and the source-target gap"
_PROGRESS_HEADERS = ("task", "core suite", "same-budget test", "RL on source: source return",
                     "RL on source: target return", "kept", "RL on target (oracle runs)", "RL on source, normalized",
                     "P(oracle > RL on source)")
_PROGRESS_TEXT_COLUMNS = 3
_PROGRESS_NOTE = ("Not submissions: the published runs of the two reference points (`leaderboard/reference-runs`, "
                  "RL on source evaluated on both sides of each task), as they come in: each core task's source-target "
                  "gap, and how far the oracle is from RL on source there. "
                  "Returns are means over training seeds, their number in brackets; kept = target / source return; "
                  "the normalized score and P(oracle > RL on source) use the task's oracle reference (for a "
                  "candidate without one, its published oracle runs), '-' where neither exists yet. Core suite: "
                  "'yes' for the protocol version's core suite, 'candidate' for "
                  "a pair outside it whose runs are published to test it. Same-budget test (PROTOCOL.md §9, "
                  "`offdyn-bench protocol admission`): whether, over 5 seeds each side, the oracle beats the zero "
                  "command, beats RL on source with P >= 0.9, and RL on source scores at most 50 normalized; "
                  "'undecided' while a side has fewer seeds (unless no result of the missing seeds could lift P "
                  "to 0.9) or the task no oracle or reference.")


def _progress_cells(row: ReferenceProgress) -> list[tuple[str, str | float | None]]:
    """(text, sort value) per column of a reference-progress row."""
    def mean(values: Sequence[float]) -> tuple[str, float | None]:
        if not values:
            return "-", None
        value = sum(values) / len(values)
        return f"{value:.1f} ({len(values)})", value

    def number(value: float | None, form: str = "{:.1f}") -> tuple[str, float | None]:
        return ("-", None) if value is None else (form.format(value), value)

    gap = row.rl_on_source
    if gap is None:
        source_side = [("-", None)] * 3 + [mean(row.oracle_seed_means)] + [("-", None)] * 2
    else:
        source_side = [mean(gap.source_seed_means), mean(gap.target_seed_means), number(gap.kept, "{:.2f}"),
                       mean(row.oracle_seed_means), number(gap.normalized_target),
                       number(gap.oracle_better_probability, "{:.2f}")]
    membership = "yes" if row.in_core_suite else "candidate"
    admission = row.admission
    verdict = admission.verdict if admission is not None else "-"
    return [(row.task, row.task), (membership, membership), (verdict, verdict), *source_side]


def _progress_markdown(progress: Mapping[str, Sequence[ReferenceProgress]]) -> list[str]:
    lines = []
    for budget, rows in sorted(progress.items()):
        lines += ["", f"## {_PROGRESS_TITLE} (`{budget}`)", "", _PROGRESS_NOTE, "",
                  "| " + " | ".join(_PROGRESS_HEADERS) + " |",
                  "|" + "---|" * _PROGRESS_TEXT_COLUMNS + "---:|" * (len(_PROGRESS_HEADERS) - _PROGRESS_TEXT_COLUMNS)]
        for row in rows:
            lines.append("| " + " | ".join(_markdown_cell(text) for text, _ in _progress_cells(row)) + " |")
    return lines


def _progress_html(progress: Mapping[str, Sequence[ReferenceProgress]]) -> str:
    parts = []
    for budget, rows in sorted(progress.items()):
        body = "".join("<tr>" + "".join(_cell(text, sort, is_text=index < _PROGRESS_TEXT_COLUMNS)
                                        for index, (text, sort) in enumerate(_progress_cells(row))) + "</tr>"
                       for row in rows)
        parts.append(f"<h2>{_PROGRESS_TITLE} ({html.escape(budget)})</h2>"
                     f'<p class="note">{html.escape(_PROGRESS_NOTE)}</p>'
                     f'<table class="sortable" id="reference-runs-{html.escape(budget)}"><thead><tr>'
                     f"{_header_row(_PROGRESS_HEADERS, text_columns=_PROGRESS_TEXT_COLUMNS)}</tr></thead><tbody>{body}</tbody></table>")
    return "".join(parts)


_CLAIMS_TITLE = "The papers' headline claims on the reference runs"
_CLAIMS_HEADERS = ("claim", "paper", "task", "dataset", "better: return (seeds)", "worse: return (seeds)", "verdict",
                   "P(better > worse)")
_CLAIMS_TEXT_COLUMNS = 4
_CLAIMS_NOTE = ("From the published runs above and those of the adapted methods (`offdyn-bench protocol claims` on "
                "the same records): each claim wherever both of its methods have runs on a task. Returns are mean "
                "target returns over training seeds; the verdict compares the means (at least twice, or more than, "
                "as the claim says); P is the probability of improvement over seeds. '(not claimed here)' marks a "
                "task outside the paper's own settings; a caveat, what a method's trainings were too short for "
                "(DARC's reward correction starts at step 100,000, the whole lite budget).")


def _claim_cells(check: ClaimCheck) -> list[tuple[str, str | float | None]]:
    claim = check.claim
    # A verdict against a training too short to run its method's mechanism says so beside it.
    verdict = check.verdict_text + "".join(f" (caveat: {caveat})" for caveat in check.caveats)
    task = check.task + ("" if check.claimed_on_task else " (not claimed here)")
    return [(claim.name, claim.name), (claim.paper, claim.paper), (task, task), (check.dataset, check.dataset),
            (f"{claim.better}: {check.better_return:.1f} ({check.better_seeds})", check.better_return),
            (f"{claim.worse}: {check.worse_return:.1f} ({check.worse_seeds})", check.worse_return),
            (verdict, verdict), (f"{check.probability_of_improvement:.2f}", check.probability_of_improvement)]


def _claims_markdown(claims: Mapping[str, Sequence[ClaimCheck]]) -> list[str]:
    lines = []
    for budget, checks in sorted(claims.items()):
        lines += ["", f"## {_CLAIMS_TITLE} (`{budget}`)", "", _CLAIMS_NOTE, "",
                  "| " + " | ".join(_CLAIMS_HEADERS) + " |",
                  "|" + "---|" * _CLAIMS_TEXT_COLUMNS + "---:|---:|---|---:|"]
        lines += ["| " + " | ".join(_markdown_cell(text) for text, _ in _claim_cells(check)) + " |" for check in checks]
    return lines


def _claims_html(claims: Mapping[str, Sequence[ClaimCheck]]) -> str:
    parts = []
    for budget, checks in sorted(claims.items()):
        body = "".join("<tr>" + "".join(_cell(text, sort, is_text=index < _CLAIMS_TEXT_COLUMNS or index == 6)
                                        for index, (text, sort) in enumerate(_claim_cells(check))) + "</tr>"
                       for check in checks)
        parts.append(f"<h2>{html.escape(_CLAIMS_TITLE)} ({html.escape(budget)})</h2>"
                     f'<p class="note">{html.escape(_CLAIMS_NOTE)}</p>'
                     f'<table class="sortable" id="reference-claims-{html.escape(budget)}"><thead><tr>'
                     f"{_header_row(_CLAIMS_HEADERS, text_columns=_CLAIMS_TEXT_COLUMNS)}</tr></thead><tbody>{body}"
                     "</tbody></table>")
    return "".join(parts)


def render_markdown(board: Board, progress: Mapping[str, Sequence[ReferenceProgress]] | None = None,
                    claims: Mapping[str, Sequence[ClaimCheck]] | None = None) -> str:
    """The README table: method, track, budget, IQM [95% CI], mean, optimality gap, per-task raw means;
    then, with ``progress``, the reference runs published so far, and with ``claims`` the papers'
    claims checked on them."""
    from offdyn_bench import protocol

    lines = [f"Protocol {protocol.PROTOCOL_VERSION}; {len(board.entries)} submission(s). Scores are normalized "
             "(0 = random policy, 100 = oracle, SAC trained on the target at the same budget) and recomputed "
             "from the raw returns; IQM, mean and optimality gap with stratified-bootstrap 95% intervals. "
             "Per-task columns are raw mean target returns.", ""]
    header = ["method", "track", "budget", "seeds", "IQM [95% CI]", "mean [95% CI]", "optimality gap [95% CI]",
              *board.tasks]
    lines.append("| " + " | ".join(header) + " |")
    lines.append("|" + "|".join(["---"] * 3 + ["---:"] * (len(header) - 3)) + "|")
    for entry in board.entries:
        submission = entry.submission
        seeds = len(next(iter(submission.tasks.values())).seeds)
        cells = [_method_label(entry), submission.track, submission.budget, str(seeds), _interval_text(entry.iqm),
                 _interval_text(entry.mean), _interval_text(entry.optimality_gap),
                 *(_number(entry.raw_mean[task]) for task in board.tasks)]
        lines.append("| " + " | ".join(_markdown_cell(c) for c in cells) + " |")
    lines.append("")
    lines.extend(f"- {_markdown_cell(note)}" for note in _normalization_notes(board))
    lines.extend(_progress_markdown(progress or {}))
    lines.extend(_claims_markdown(claims or {}))
    return "\n".join(lines) + "\n"


# --------------------------------------------------------------------------------------------
# Plots
# --------------------------------------------------------------------------------------------

_COLORS = ("#1f77b4", "#d62728", "#2ca02c", "#ff7f0e", "#9467bd", "#8c564b", "#e377c2", "#7f7f7f",
           "#bcbd22", "#17becf")


def _png(figure: object) -> str:
    buffer = io.BytesIO()
    # No "Software" (matplotlib's version) and no dates: the bytes depend on the data alone.
    figure.savefig(buffer, format="png", dpi=100, metadata={"Software": None})  # type: ignore[attr-defined]
    return base64.b64encode(buffer.getvalue()).decode("ascii")


def _profile_plots(board: Board) -> list[tuple[str, str]]:
    """(title, base64 PNG) of one performance-profile figure per track and budget with scored entries."""
    # A bare Figure (no pyplot): no global state, and savefig picks the Agg canvas for PNG.
    from matplotlib.figure import Figure

    from leaderboard.scores import PROFILE_TAUS

    groups: dict[tuple[str, str], list[Entry]] = {}
    for entry in board.entries:
        if entry.normalized is not None:
            groups.setdefault(entry.group, []).append(entry)
    plots = []
    for (track, budget), entries in sorted(groups.items()):
        figure = Figure(figsize=(6.4, 4.0))
        axes = figure.add_subplot()
        for index, entry in enumerate(sorted(entries, key=lambda e: e.submission.method)):
            profile, low, high = performance_profile(entry)
            color = _COLORS[index % len(_COLORS)]
            axes.plot(PROFILE_TAUS, profile, color=color, label=_method_label(entry))
            axes.fill_between(PROFILE_TAUS, low, high, color=color, alpha=0.2, linewidth=0)
        axes.set_xlabel("normalized score τ")
        axes.set_ylabel("fraction of runs with score > τ")
        axes.set_ylim(-0.02, 1.02)
        axes.grid(alpha=0.3)
        axes.legend(fontsize="small")
        scored = len(board.normalizations[budget].scored_tasks)
        axes.set_title(f"{track}, {budget} ({scored} tasks)")
        figure.tight_layout()
        plots.append((f"Performance profiles: {track}, {budget}", _png(figure)))
    return plots


def _learning_curve_plot(board: Board) -> str | None:
    """One base64 PNG with a panel per core task: mean in-training target return of every entry that
    submitted a learning curve (shaded: the range across training seeds)."""
    import numpy as np
    from matplotlib.figure import Figure

    with_curves = [e for e in board.entries if any(r.learning_curve for r in e.submission.tasks.values())]
    if not with_curves:
        return None
    columns = min(4, len(board.tasks))
    rows = math.ceil(len(board.tasks) / columns)
    figure = Figure(figsize=(3.6 * columns, 2.8 * rows))
    ordered = sorted(with_curves, key=lambda e: e.submission.key)
    legend_shown = False
    for position, task in enumerate(board.tasks):
        axes = figure.add_subplot(rows, columns, position + 1)
        plotted = False
        for index, entry in enumerate(ordered):
            curve = entry.submission.tasks[task].learning_curve
            if not curve:
                continue
            plotted = True
            steps = np.array([p.step for p in curve], dtype=np.float64)
            values = np.array([p.target_return for p in curve], dtype=np.float64)
            color = _COLORS[index % len(_COLORS)]
            label = f"{_method_label(entry)} ({entry.submission.track}, {entry.submission.budget})"
            axes.plot(steps, values.mean(axis=1), color=color, label=label, linewidth=1.2)
            axes.fill_between(steps, values.min(axis=1), values.max(axis=1), color=color, alpha=0.15,
                              linewidth=0)
        axes.set_title(task, fontsize="small")
        axes.tick_params(labelsize="x-small")
        axes.grid(alpha=0.3)
        if not plotted:
            # A submission may carry curves for some tasks only (RL on source's second task scores
            # a policy trained for another): say so rather than leave an empty frame.
            axes.text(0.5, 0.5, "no learning curve submitted", ha="center", va="center", fontsize="x-small",
                      transform=axes.transAxes)
            axes.set_xticks([])
            axes.set_yticks([])
        elif not legend_shown:
            axes.legend(fontsize="x-small")
            legend_shown = True
    figure.supxlabel("training step")
    figure.supylabel("target return (raw)")
    figure.tight_layout()
    return _png(figure)


# --------------------------------------------------------------------------------------------
# HTML
# --------------------------------------------------------------------------------------------

_STYLE = """
body { font-family: system-ui, sans-serif; margin: 1.5rem; color: #111; }
table { border-collapse: collapse; margin: 0.5rem 0 1.5rem; font-size: 0.9rem; }
th, td { border: 1px solid #ccc; padding: 0.25rem 0.5rem; text-align: right; white-space: nowrap; }
th { background: #f3f3f3; }
td.text, th.text { text-align: left; }
table.sortable th { cursor: pointer; user-select: none; }
table.sortable th[aria-sort="ascending"]::after { content: " \\25B2"; }
table.sortable th[aria-sort="descending"]::after { content: " \\25BC"; }
.note { color: #444; max-width: 60rem; }
img { max-width: 100%; }
"""

# Plain JS: a click on a header sorts the body rows by that column's data-sort values (numbers
# numerically, text alphabetically, empty cells last); a second click reverses the order.
_SCRIPT = """
document.querySelectorAll("table.sortable").forEach(function (table) {
  var headers = table.querySelectorAll("thead th");
  headers.forEach(function (header, column) {
    header.addEventListener("click", function () {
      var ascending = header.getAttribute("aria-sort") !== "ascending";
      headers.forEach(function (h) { h.removeAttribute("aria-sort"); });
      header.setAttribute("aria-sort", ascending ? "ascending" : "descending");
      var body = table.tBodies[0];
      var rows = Array.prototype.slice.call(body.rows);
      var key = function (row) { return row.cells[column].getAttribute("data-sort"); };
      var numeric = rows.every(function (row) { var k = key(row); return k === "" || !isNaN(parseFloat(k)); });
      rows.sort(function (a, b) {
        var x = key(a), y = key(b);
        if (x === "" || y === "") { return x === y ? 0 : (x === "" ? 1 : -1); }
        var order = numeric ? parseFloat(x) - parseFloat(y) : (x < y ? -1 : (x > y ? 1 : 0));
        return ascending ? order : -order;
      });
      rows.forEach(function (row) { body.appendChild(row); });
    });
  });
});
"""


def _cell(text: str, sort: str | float | None, *, is_text: bool = False) -> str:
    sort_text = "" if sort is None else (repr(float(sort)) if isinstance(sort, float) else sort)
    css = ' class="text"' if is_text else ""
    return f'<td{css} data-sort="{html.escape(sort_text)}">{html.escape(text)}</td>'


def _method_cell(entry: Entry) -> str:
    submission = entry.submission
    label = html.escape(_method_label(entry))
    if submission.code_url:
        commit = f" @ {html.escape(submission.commit[:12])}" if submission.commit else ""
        label = f'<a href="{html.escape(submission.code_url)}">{label}</a>{commit}'
    title = html.escape(submission.description)
    return f'<td class="text" data-sort="{html.escape(submission.method)}" title="{title}">{label}</td>'


def _header_row(headers: Sequence[str], *, text_columns: int) -> str:
    text = ' class="text"'
    return "".join(f'<th{text if i < text_columns else ""} scope="col">{html.escape(h)}</th>'
                   for i, h in enumerate(headers))


def _main_table(board: Board) -> str:
    headers = ["method", "track", "budget", "seeds", "IQM [95% CI]", "mean [95% CI]", "optimality gap [95% CI]",
               *board.tasks]
    head = _header_row(headers, text_columns=3)
    rows = []
    for entry in board.entries:
        submission = entry.submission
        seeds = len(next(iter(submission.tasks.values())).seeds)
        cells = [_method_cell(entry), _cell(submission.track, submission.track, is_text=True),
                 _cell(submission.budget, submission.budget, is_text=True), _cell(str(seeds), float(seeds))]
        for interval in (entry.iqm, entry.mean, entry.optimality_gap):
            cells.append(_cell(_interval_text(interval), None if interval is None else interval.point))
        for task in board.tasks:
            cells.append(_cell(_number(entry.raw_mean[task]), entry.raw_mean[task]))
        rows.append("<tr>" + "".join(cells) + "</tr>")
    return (f'<table class="sortable" id="leaderboard"><thead><tr>{head}</tr></thead>'
            f'<tbody>{"".join(rows)}</tbody></table>')


def _breakdown_table(board: Board) -> str:
    """Per method and task: raw mean ± std across seeds, and the normalized mean where it exists."""
    headers = ["method", "track", "budget", *board.tasks]
    head = _header_row(headers, text_columns=3)
    rows = []
    for entry in board.entries:
        submission = entry.submission
        scored = board.normalizations[submission.budget].scored_tasks
        cells = [_method_cell(entry), _cell(submission.track, submission.track, is_text=True),
                 _cell(submission.budget, submission.budget, is_text=True)]
        for task in board.tasks:
            text = f"{entry.raw_mean[task]:.1f} ± {entry.raw_seed_std[task]:.1f}"
            sort: float = entry.raw_mean[task]
            if entry.normalized is not None and task in scored:
                normalized = float(entry.normalized[:, scored.index(task)].mean())
                text += f" ({normalized:.1f})"
                sort = normalized
            cells.append(_cell(text, sort))
        rows.append("<tr>" + "".join(cells) + "</tr>")
    return (f'<table class="sortable" id="per-task"><thead><tr>{head}</tr></thead>'
            f'<tbody>{"".join(rows)}</tbody></table>')


def _improvement_tables(board: Board) -> str:
    parts = []
    groups = sorted({(i.track, i.budget) for i in board.improvements})
    for track, budget in groups:
        improvements = {(i.x, i.y): i.probability for i in board.improvements
                        if (i.track, i.budget) == (track, budget)}
        methods = sorted({x for x, _ in improvements})
        head = '<th class="text">P(row &gt; column)</th>' + "".join(f"<th>{html.escape(m)}</th>" for m in methods)
        rows = []
        for x in methods:
            cells = [f'<th class="text" scope="row">{html.escape(x)}</th>']
            for y in methods:
                probability = improvements.get((x, y))
                cells.append("<td>–</td>" if probability is None else
                             f"<td>{probability.point:.2f} [{probability.low:.2f}, {probability.high:.2f}]</td>")
            rows.append("<tr>" + "".join(cells) + "</tr>")
        parts.append(f"<h3>{html.escape(track)}, {html.escape(budget)}</h3>"
                     f"<table><thead><tr>{head}</tr></thead><tbody>{''.join(rows)}</tbody></table>")
    if not parts:
        return '<p class="note">Needs two or more methods with normalized scores on one track and budget.</p>'
    return "".join(parts)


def _normalization_html(normalizations: Sequence[Normalization], task_count: int) -> str:
    items = []
    for normalization in normalizations:
        budget = html.escape(normalization.budget)
        if normalization.scored_tasks:
            items.append(f"<li>Budget <code>{budget}</code>: normalized over {len(normalization.scored_tasks)} of "
                         f"{task_count} core tasks ({html.escape(', '.join(normalization.scored_tasks))}).</li>")
        else:
            items.append(f"<li>Budget <code>{budget}</code>: no normalized scores yet; no core task has both "
                         "references at this budget.</li>")
        for task, reason in sorted(normalization.excluded.items()):
            items.append(f"<li>Excluded at <code>{budget}</code>: <code>{html.escape(task)}</code>: "
                         f"{html.escape(reason)}</li>")
        for task, text in _below_zero_command(normalization):
            items.append(f"<li>Oracle below the zero command at <code>{budget}</code>: "
                         f"<code>{html.escape(task)}</code>: {html.escape(text)}</li>")
    return f'<ul class="note">{"".join(items)}</ul>' if items else ""


def render_html(board: Board, progress: Mapping[str, Sequence[ReferenceProgress]] | None = None,
                claims: Mapping[str, Sequence[ClaimCheck]] | None = None) -> str:
    from offdyn_bench import protocol

    normalizations = [board.normalizations[b] for b in sorted(board.normalizations)]
    profiles = _profile_plots(board)
    curves = _learning_curve_plot(board)
    profile_html = "".join(f'<h3>{html.escape(title)}</h3><img alt="{html.escape(title)}" '
                           f'src="data:image/png;base64,{png}">' for title, png in profiles) or \
        '<p class="note">No entry has normalized scores yet.</p>'
    curve_html = (f'<img alt="Learning curves" src="data:image/png;base64,{curves}">' if curves else
                  '<p class="note">No submission includes learning curves.</p>')
    return f"""<!DOCTYPE html>
<html lang="en">
<head>
<meta charset="utf-8">
<title>offdyn-bench leaderboard</title>
<style>{_STYLE}</style>
</head>
<body>
<h1>offdyn-bench leaderboard</h1>
<p class="note">Protocol {html.escape(protocol.PROTOCOL_VERSION)}, {len(board.entries)} submission(s).
Every score is recomputed from the submitted raw per-seed, per-episode target returns. Normalized score =
100 &times; (J &minus; J<sub>random</sub>) / (J<sub>oracle</sub> &minus; J<sub>random</sub>), per training seed;
IQM, mean and optimality gap (shortfall from 100) with stratified-bootstrap 95% intervals. Per-task columns
are raw mean target returns. Click a column header to sort.</p>
{_normalization_html(normalizations, len(board.tasks))}
<h2>Leaderboard</h2>
{_main_table(board)}
<h2>Per task</h2>
<p class="note">Raw mean target return &plusmn; standard deviation across training seeds; the normalized
mean in parentheses where the task has both references.</p>
{_breakdown_table(board)}
<h2>Probability of improvement</h2>
<p class="note">P(X &gt; Y): the probability that a run of the row's method beats a run of the column's
method on a task drawn uniformly from the scored tasks (ties count 1/2), with its 95% interval.</p>
{_improvement_tables(board)}
{_progress_html(progress or {})}
{_claims_html(claims or {})}
<h2>Performance profiles</h2>
{profile_html}
<h2>Learning curves</h2>
{curve_html}
<script>{_SCRIPT}</script>
</body>
</html>
"""


def build_site(store: Path, out: Path, *, references: Path | None = None,
               reference_runs: Path | None = None) -> tuple[Path, Path]:
    """Render ``store`` into ``out/leaderboard.md`` and ``out/index.html``; both written atomically.
    ``reference_runs`` (e.g. the repository's ``leaderboard/reference-runs``) adds the reference runs
    published so far."""
    from leaderboard.reference_runs import reference_claims, reference_progress
    from leaderboard.scores import score_board
    from leaderboard.store import load_store

    board = score_board(load_store(store), references=references)
    progress = reference_progress(reference_runs, references=references) if reference_runs is not None else None
    claims = reference_claims(reference_runs) if reference_runs is not None else None
    markdown, page = render_markdown(board, progress, claims), render_html(board, progress, claims)
    try:
        out.mkdir(parents=True, exist_ok=True)
        write_file_atomic(out / "leaderboard.md", markdown.encode())
        write_file_atomic(out / "index.html", page.encode())
    except OSError as error:
        raise OffdynError(f"--out {str(out)!r}: cannot write the leaderboard there ({error.strerror or error}); "
                          "expected a folder this user can create and write") from None
    return out / "leaderboard.md", out / "index.html"
