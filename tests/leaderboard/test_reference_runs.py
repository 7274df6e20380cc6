"""The published reference runs: every record there scores under the protocol, the numbers the
repository publishes from them (the oracle references, PROTOCOL.md's gap table) are recomputed from
them, and publishing refuses what is not a finished protocol evaluation without writing anything."""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import pytest

from leaderboard.reference_runs import (
    REFERENCE_RUNS_DIR,
    RECORD_FILES,
    check_reference_curve,
    check_reference_record,
    publish_reference_runs,
    reference_progress,
)
from leaderboard.submission import SubmissionError
from offdyn_bench.protocol.claims import NO_DATASET

REPO = Path(__file__).resolve().parents[2]
PUBLISHED = sorted(REFERENCE_RUNS_DIR.glob("*/*/*/*/evaluation*.json"))
PUBLISHED_CURVES = sorted(REFERENCE_RUNS_DIR.glob("*/*/*/*/metrics.jsonl"))


def _parts(path: Path) -> tuple[str, str, str, str, str]:
    budget, method, task, label, name = path.relative_to(REFERENCE_RUNS_DIR).parts
    return budget, method, task, label, name


def _records(method: str, task: str | None = None, name: str | None = None) -> list[dict]:
    return [json.loads(path.read_text()) for path in PUBLISHED
            if _parts(path)[1] == method and task in (None, _parts(path)[2]) and name in (None, _parts(path)[4])]


def test_the_repository_publishes_reference_runs_of_both_reference_methods():
    methods = {_parts(path)[1] for path in PUBLISHED}
    assert {"sac-source", "sac-target"} <= methods
    # RL on source is published with both sides of each task it has a target record of.
    for path in PUBLISHED:
        if _parts(path)[1] == "sac-source" and path.name == "evaluation.json":
            assert (path.parent / "evaluation-source.json").exists(), path


@pytest.mark.parametrize("path", PUBLISHED, ids=lambda p: str(p.relative_to(REFERENCE_RUNS_DIR)))
def test_every_published_record_is_a_complete_protocol_evaluation_where_it_lies(path):
    budget, method, task, label, name = _parts(path)
    record = json.loads(path.read_text())
    check_reference_record(path, record, method, task, label, RECORD_FILES[name])
    assert record["budget"] == budget and record["protocol_version"] == "1.0"


@pytest.mark.parametrize("path", PUBLISHED_CURVES, ids=lambda p: str(p.relative_to(REFERENCE_RUNS_DIR)))
def test_every_published_learning_curve_belongs_to_the_training_its_record_scores(path):
    record = json.loads((path.parent / "evaluation.json").read_text())
    check_reference_curve(path, record)
    # The curve's last point is the training's own evaluation of the final policy: the same
    # policy the record scores, on other episodes, so the two agree in scale.
    final = json.loads(path.read_text().splitlines()[-1])
    assert final["step"] == record["steps"]


def test_the_shipped_oracle_references_are_the_published_sac_target_runs():
    """assets/reference_scores.json's lite oracles, recomputed from the published records: the same
    mean, the same per-seed means, and the same policies (sha256)."""
    scores = json.loads((REPO / "assets" / "reference_scores.json").read_text())["tasks"]
    oracles = {task: entry["oracle"]["lite"] for task, entry in scores.items() if "lite" in entry.get("oracle", {})}
    assert len(oracles) >= 5
    for task, oracle in oracles.items():
        records = sorted(_records("sac-target", task, "evaluation.json"), key=lambda r: r["seeds"][0]["seed"])
        assert [r["seeds"][0]["seed"] for r in records] == oracle["provenance"]["seeds"], task
        returns = [x for record in records for x in record["seeds"][0]["returns"]]
        assert returns == oracle["returns"], task
        assert sum(returns) / len(returns) == pytest.approx(oracle["mean_return"], rel=1e-12), task
        shipped = {run["path"].rsplit("/", 1)[-1]: run["policy_sha256"] for run in oracle["provenance"]["runs"]}
        for record in records:
            assert record["agent"]["policy_sha256"] == shipped[f"seed-{record['seeds'][0]['seed']}"], task


def test_protocol_md_learning_curve_table_is_what_protocol_curves_computes_from_the_published_curves():
    from offdyn_bench.protocol.curves import curves_markdown, read_curves

    text = (REPO / "PROTOCOL.md").read_text()
    header = "| budget/method/task | seeds |"
    assert header in text, "PROTOCOL.md §9 shows the published runs' learning curves"
    shown = []
    for line in text[text.index(header):].splitlines()[2:]:
        if not line.strip().startswith("|"):
            break
        shown.append(line.strip())
    computed = [line for line in curves_markdown(read_curves(PUBLISHED_CURVES)).splitlines()[2:]
                if line.startswith("|")]
    assert shown == computed


def _protocol_gap_tables() -> list[tuple[str, dict[str, tuple[str, ...]]]]:
    """PROTOCOL.md §9's gap tables (one per robot): the text before each, and its rows (task -> its
    cells after the task)."""
    text = (REPO / "PROTOCOL.md").read_text()
    section = text[text.index("## 9."):]
    header = "| task | RL on source, source / target return |"
    pieces = section.split(header)
    tables = []
    for before, table in zip(pieces, pieces[1:]):
        rows = {}
        for line in table.splitlines()[2:]:
            line = line.strip()  # the tables are indented inside list items
            if not line.startswith("| `"):
                break
            cells = [cell.strip() for cell in line.strip("|").split("|")]
            rows[cells[0].strip("`")] = tuple(cells[1:])
        # The text just before a table introduces it (whitespace normalized: it wraps across lines).
        tables.append((" ".join(before[-800:].split()), rows))
    return tables


def test_protocol_md_gap_table_is_what_protocol_gap_computes_from_the_published_runs():
    from offdyn_bench.protocol.gap import measure_gaps

    tables = _protocol_gap_tables()
    rows = {task: cells for _, table in tables for task, cells in table.items()}
    assert len(rows) >= 8 and {"hopper-gravity-0.5", "walker2d-gravity-2.0"} <= set(rows)
    gaps = {gap.task: gap for gap in measure_gaps(_records("sac-source"))}
    for task, cells in rows.items():
        gap = gaps[task]
        seeds = len(gap.target_seed_means)
        assert len(gap.source_seed_means) == seeds, task
        def shown(value, form):
            return "-" if value is None else form.format(value)

        assert cells == (f"{gap.source_return:.1f} / {gap.target_return:.1f}", f"{gap.kept:.2f}",
                         shown(gap.normalized_target, "{:.1f}"), shown(gap.oracle_better_probability, "{:.2f}")), task
    # The text introducing each table says over how many seeds it is.
    for before, table in tables:
        counts = {len(gaps[task].target_seed_means) for task in table}
        assert len(counts) == 1, sorted(table)
        assert f"over {counts.pop()} `sac-source` lite seeds" in before, sorted(table)


def test_protocol_md_names_the_core_pairs_that_pass_the_admission_test_on_the_published_runs():
    """§9's decision names the core pairs where RL on source clearly fails at lite: exactly those that
    `protocol admission` passes on the published runs; every other core pair fails it."""
    import re

    from offdyn_bench.protocol import CORE_SUITE
    from offdyn_bench.protocol.gap import admit, measure_gaps

    lite = [record for record in _records("sac-source") if record["budget"] == "lite"]
    verdicts = {one.task: one.verdict for one in map(admit, measure_gaps(lite)) if one.task in CORE_SUITE}
    assert set(verdicts) == set(CORE_SUITE)
    text = " ".join((REPO / "PROTOCOL.md").read_text().split())
    sentence = text[text.index("With every core pair measured at `lite`"):]
    sentence = sentence[:sentence.index("On the other")]
    named = set(re.findall(r"`([a-z0-9.-]+)`", sentence)) - {"lite"}
    assert named == {task for task, verdict in verdicts.items() if verdict == "passes"}
    assert {verdict for task, verdict in verdicts.items() if task not in named} == {"fails"}
    assert "offdyn-bench protocol admission" in text


def test_the_boards_same_budget_test_is_protocol_admissions_on_the_published_runs():
    """The board's progress table and `offdyn-bench protocol admission` give every published pair the
    same verdict. A candidate has no recorded oracle: its oracle runs are its oracle in both (the
    board once left them out and called `hopper-gravity-5.0`, which the command fails, undecided)."""
    from offdyn_bench.protocol.gap import admit, measure_gaps

    lite = [record for record in _records("sac-source") + _records("sac-target") if record["budget"] == "lite"]
    command = {one.task: (one.verdict, one.reason) for one in map(admit, measure_gaps(lite))}
    board = {row.task: (row.admission.verdict, row.admission.reason)
             for row in reference_progress()["lite"] if row.admission is not None}
    assert board == command
    assert board["hopper-gravity-5.0"][0] == "fails" and board["halfcheetah-gravity-5.0"][0] == "passes"


# Publishing: a sweep's out folder, here built from the published records themselves.


# The two reference methods' runs of one task: the tests below pin what a sweep of exactly these
# gives, so publishing another method's runs of this task leaves them as they are.
_FIXTURE_RUNS = [path for path in PUBLISHED
                 if _parts(path)[2] == "hopper-gravity-0.5" and _parts(path)[1] in ("sac-source", "sac-target")]


@pytest.fixture
def sweep_out(tmp_path) -> Path:
    out = tmp_path / "sweep"
    for path in _FIXTURE_RUNS:
        _, method, task, label, name = _parts(path)
        target = out / "runs" / method / task / label / name
        target.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(path, target)
    (out / "runs" / "sac-target" / "hopper-gravity-0.5" / "seed-9").mkdir()  # still training
    return out


def _tree(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()} \
        if root.exists() else {}


def test_publishing_copies_records_byte_for_byte_and_again_changes_nothing(sweep_out, tmp_path):
    dest = tmp_path / "published"
    report = publish_reference_runs(sweep_out, dest)
    assert len(report.written) == len(_FIXTURE_RUNS)
    assert report.unfinished == (sweep_out / "runs" / "sac-target" / "hopper-gravity-0.5" / "seed-9",)
    for path in report.written:
        _, method, task, label, name = path.relative_to(dest).parts
        assert path.read_bytes() == (sweep_out / "runs" / method / task / label / name).read_bytes()
        assert path.read_bytes() == (REFERENCE_RUNS_DIR / "lite" / method / task / label / name).read_bytes()
    again = publish_reference_runs(sweep_out, dest)
    assert again.written == () and sorted(again.unchanged) == sorted(report.written)
    only = publish_reference_runs(sweep_out, tmp_path / "only-target", methods=["sac-target"])
    assert {p.relative_to(tmp_path / "only-target").parts[1] for p in only.written} == {"sac-target"}


def _write_curve(run: Path, steps: range, returns=lambda step: [step / 100.0]) -> Path:
    path = run / "metrics.jsonl"
    path.write_text("".join(json.dumps({"step": step, "target_return": returns(step), "wall_time_s": step / 50})
                            + "\n" for step in steps))
    return path


def test_a_trainings_learning_curve_is_published_beside_its_record(sweep_out, tmp_path):
    trained = sweep_out / "runs" / "sac-target" / "hopper-gravity-0.5" / "seed-0"
    curve = _write_curve(trained, range(5000, 100001, 5000))
    _write_curve(sweep_out / "runs" / "sac-target" / "hopper-gravity-0.5" / "seed-9", range(5000, 20001, 5000))
    dest = tmp_path / "published"
    report = publish_reference_runs(sweep_out, dest)
    published = dest / "lite" / "sac-target" / "hopper-gravity-0.5" / "seed-0" / "metrics.jsonl"
    assert published in report.written and published.read_bytes() == curve.read_bytes()
    # Only the finished training's curve: the unfinished run publishes nothing.
    assert [p.relative_to(dest) for p in dest.rglob("metrics.jsonl")] == [published.relative_to(dest)]
    assert published in publish_reference_runs(sweep_out, dest).unchanged
    curve.write_text(curve.read_text().replace('"step": 100000, "target_return": [1000.0]',
                                               '"step": 100000, "target_return": [999.0]'))
    with pytest.raises(SubmissionError, match=r"1 published record\(s\) differ.*seed-0/metrics.jsonl"):
        publish_reference_runs(sweep_out, dest)
    assert json.loads(published.read_text().splitlines()[-1])["target_return"] == [1000.0]


@pytest.mark.parametrize("write, message", [
    (lambda run: _write_curve(run, range(5000, 50001, 5000)),
     r"the curve ends at step 50000, but the evaluation beside it scores the policy of step 100000"),
    (lambda run: _write_curve(run, [5000, 15000, 10000, 100000]), r"step 10000 follows step 15000"),
    (lambda run: _write_curve(run, range(5000, 100001, 5000), lambda step: [1.0, 2.0]),
     r"target_return has 2 per-seed values; the evaluation next to it has 1 seeds"),
    (lambda run: _write_curve(run, range(5000, 100001, 5000), lambda step: ["1.0"]),
     r"step 5000: a target return that is not a finite number"),
    (lambda run: _write_curve(run, range(5000, 100001, 5000), lambda step: [1e999]), r"Infinity is not valid JSON"),
    (lambda run: (run / "metrics.jsonl").write_text('{"step": 5000, "target_return": [NaN]}\n'),
     r"NaN is not valid JSON"),
    (lambda run: (run / "metrics.jsonl").write_text('{"step": "5000", "target_return": [1.0]}\n'),
     r"a step that is not a positive integer"),
    (lambda run: (run / "metrics.jsonl").write_text("\n"), r"no evaluation"),
    (lambda run: (run / "metrics.jsonl").write_text('[1, 2]\n'), r'expected an object with "step" and "target_return"'),
])
def test_publishing_refuses_a_curve_that_is_not_the_scored_trainings_and_writes_nothing(
        sweep_out, tmp_path, write, message):
    run = sweep_out / "runs" / "sac-target" / "hopper-gravity-0.5" / "seed-2"
    write(run)
    dest = tmp_path / "published"
    with pytest.raises(SubmissionError, match=message) as caught:
        publish_reference_runs(sweep_out, dest)
    assert str(run / "metrics.jsonl") in str(caught.value)
    assert not dest.exists()


def test_a_published_number_changes_only_when_asked(sweep_out, tmp_path):
    dest = tmp_path / "published"
    publish_reference_runs(sweep_out, dest)
    before = _tree(dest)
    record_path = sweep_out / "runs" / "sac-target" / "hopper-gravity-0.5" / "seed-0" / "evaluation.json"
    record = json.loads(record_path.read_text())
    record["seeds"][0]["returns"][0] += 1.0
    record_path.write_text(json.dumps(record, indent=1))
    with pytest.raises(SubmissionError, match=r"1 published record\(s\) differ from the sweep's: .*seed-0/"
                                              r"evaluation.json .*published numbers change only with --replace"):
        publish_reference_runs(sweep_out, dest)
    assert _tree(dest) == before
    report = publish_reference_runs(sweep_out, dest, replace=True)
    assert len(report.written) == 1 and json.loads(report.written[0].read_text()) == record


def test_a_run_reproduced_elsewhere_keeps_the_published_bytes(sweep_out, tmp_path):
    """A retraining in another folder gives the same numbers under other paths (and a curve with
    other timings): reported as reproduced, the published bytes kept; any number that differs is
    still a conflict."""
    run = sweep_out / "runs" / "sac-source" / "hopper-gravity-0.5" / "seed-0"
    _write_curve(run, range(5000, 100001, 5000))
    dest = tmp_path / "published"
    publish_reference_runs(sweep_out, dest)
    before = _tree(dest)
    for name in ("evaluation.json", "evaluation-source.json"):
        record = json.loads((run / name).read_text())
        moved = "/elsewhere/runs/sac-source/hopper-gravity-0.5/seed-0"
        record["agent"]["path"] = moved
        record["command"] = record["command"].replace(str(record["command"]).split()[3], moved)
        record["train_command"] = f"offdyn-bench train sac-source --seed 0 --out {moved}"
        # Another machine, too: where it ran, not what it measured (PROTOCOL §8).
        record["machine"] = {"cpu": "another CPU", "isa": ["avx2"], "torch_cpu_capability": "AVX2"}
        record["training_machines"] = [None, {"cpu": "another CPU"}]
        # Other code and days: the same numbers from another commit are the same measurement.
        record["source_revision"] = {"commit": "f" * 40, "modified": True}
        record["training_provenance"] = {"source_revisions": [None], "started_at": "2031-01-01T00:00:00+00:00"}
        (run / name).write_text(json.dumps(record, indent=2))
    _write_curve(run, range(5000, 100001, 5000))
    (run / "metrics.jsonl").write_text((run / "metrics.jsonl").read_text().replace('"wall_time_s": 20', '"wall_time_s": 21'))
    report = publish_reference_runs(sweep_out, dest)
    published = dest / "lite" / "sac-source" / "hopper-gravity-0.5" / "seed-0"
    assert sorted(report.reproduced) == sorted(published / name for name in
                                               ("evaluation.json", "evaluation-source.json", "metrics.jsonl"))
    assert report.written == () and _tree(dest) == before
    # The same paths with one return changed, or one policy hash: a new number, refused.
    for change in (lambda r: r["seeds"][0]["returns"].__setitem__(0, r["seeds"][0]["returns"][0] + 1e-9),
                   lambda r: r["agent"]["policy_sha256"].__setitem__("0", "0" * 64)):
        record = json.loads((run / "evaluation.json").read_text())
        saved = (run / "evaluation.json").read_text()
        change(record)
        (run / "evaluation.json").write_text(json.dumps(record))
        with pytest.raises(SubmissionError, match=r"1 published record\(s\) differ from the sweep's"):
            publish_reference_runs(sweep_out, dest)
        (run / "evaluation.json").write_text(saved)
    assert _tree(dest) == before
    curve = (run / "metrics.jsonl").read_text()
    (run / "metrics.jsonl").write_text(curve.replace('"target_return": [50.0]', '"target_return": [50.5]'))
    with pytest.raises(SubmissionError, match=r"1 published record\(s\) differ.*seed-0/metrics.jsonl"):
        publish_reference_runs(sweep_out, dest)


def _break(sweep_out: Path, change) -> Path:
    path = sweep_out / "runs" / "sac-source" / "hopper-gravity-0.5" / "seed-1" / "evaluation.json"
    record = json.loads(path.read_text())
    text = change(record)
    path.write_text(text if isinstance(text, str) else json.dumps(record))
    return path


@pytest.mark.parametrize("change, message", [
    (lambda r: r.update(task="hopper-friction-0.5"),
     r"holds 'sac-source' on 'hopper-friction-0.5', but its folder names 'sac-source' on 'hopper-gravity-0.5'"),
    (lambda r: r.update(side="source"), r"side 'source'; the file name says 'target'"),
    (lambda r: r.update(budget=None), r"budget None; only runs at a protocol budget"),
    (lambda r: r.update(protocol_conformant=False, notes=["trained for 300 steps, not at a protocol budget"]),
     r"not a protocol evaluation \(trained for 300 steps"),
    (lambda r: r["seeds"][0].update(seed=7), r"seeds \[7\]; its folder 'seed-1' names others"),
    (lambda r: r["seeds"][0].update(returns=r["seeds"][0]["returns"][:5]),
     r"seed 1: 5 episodes; the protocol scores at least 20"),
    (lambda r: r["seeds"][0]["returns"].__setitem__(3, "1e999"), r"seed 1: a return that is not a finite number"),
    (lambda r: json.dumps(r).replace('"returns": [', '"returns": [NaN, ', 1), r"NaN is not valid JSON"),
    (lambda r: "{not json", r"not valid JSON: Expecting property name"),
])
def test_publishing_refuses_what_is_not_a_finished_protocol_evaluation_and_writes_nothing(
        sweep_out, tmp_path, change, message):
    dest = tmp_path / "published"
    broken = _break(sweep_out, change)
    with pytest.raises(SubmissionError, match=message) as caught:
        publish_reference_runs(sweep_out, dest)
    assert str(broken) in str(caught.value)
    assert not dest.exists()


def test_publishing_refuses_a_folder_that_is_not_a_sweep_and_an_absent_method(sweep_out, tmp_path):
    with pytest.raises(SubmissionError, match=r"no runs/ folder; expected the out folder of `offdyn-bench sweep`"):
        publish_reference_runs(tmp_path / "nowhere", tmp_path / "published")
    present = ", ".join(sorted(path.name for path in (sweep_out / "runs").iterdir()))  # what is published there
    assert "sac-source, sac-target" in present
    with pytest.raises(SubmissionError, match=rf"no runs of dap; it has runs of {present}$"):
        publish_reference_runs(sweep_out, tmp_path / "published", methods=["dap"])
    assert not (tmp_path / "published").exists()


def _group_seeds(runs: Path, first: int, last: int, into: Path) -> Path:
    """The ``seed-N`` records under ``runs`` (one method and task) merged into one
    ``seeds-first-last`` run folder under ``into``, as a GPU lease trains seeds together."""
    group = into / f"seeds-{first}-{last}"
    group.mkdir(parents=True)
    for name in ("evaluation.json", "evaluation-source.json"):
        parts = [json.loads((runs / f"seed-{seed}" / name).read_text()) for seed in range(first, last + 1)
                 if (runs / f"seed-{seed}" / name).exists()]
        if parts:
            (group / name).write_text(json.dumps(parts[0] | {"seeds": [e for part in parts for e in part["seeds"]]}))
    return group


def test_a_training_seed_is_published_once_whatever_run_it_came_from(sweep_out, tmp_path):
    """A lease's seeds-0-4 beside a published seed-0 (or both in one sweep) would put seed 0 in the
    tree twice, which every score refuses to read: refused before anything is written, with or
    without --replace. Another target dataset's seed 0 is another cell and goes through."""
    dest = tmp_path / "published"
    publish_reference_runs(sweep_out, dest, methods=["sac-target"])
    before = _tree(dest)
    runs = sweep_out / "runs" / "sac-target" / "hopper-gravity-0.5"
    published = dest / "lite" / "sac-target" / "hopper-gravity-0.5"
    lease = tmp_path / "lease"
    _group_seeds(runs, 0, 1, lease / "runs" / "sac-target" / "hopper-gravity-0.5")
    for replace in (False, True):
        with pytest.raises(SubmissionError, match=(
                r"seeds-0-1/evaluation.json \(from .*\) would publish training seed 0 of sac-target on "
                rf"hopper-gravity-0.5 \(target side, trained on {re.escape(NO_DATASET)}\), which "
                rf"{re.escape(str(published))}/seed-0/evaluation.json holds already: a seed is published once")):
            publish_reference_runs(lease, dest, replace=replace)
        assert _tree(dest) == before
    # Both groupings in one sweep, nothing published yet: refused too.
    _group_seeds(runs, 0, 1, runs)
    with pytest.raises(SubmissionError, match=r"would publish training seed 0 of sac-target .* holds already"):
        publish_reference_runs(sweep_out, tmp_path / "fresh", methods=["sac-target"])
    assert not (tmp_path / "fresh").exists()
    # With the older folders taken out of the published tree first, the grouped run publishes.
    shutil.rmtree(published / "seed-0")
    shutil.rmtree(published / "seed-1")
    assert publish_reference_runs(lease, dest).written == (published / "seeds-0-1" / "evaluation.json",)
    # Seed 2 trained on a target dataset is another cell of the grid than seed 2 trained on none.
    record = json.loads((runs / "seed-2" / "evaluation.json").read_text())
    folder = tmp_path / "other-data" / "runs" / "sac-target" / "hopper-gravity-0.5" / "medium-v0.seed-2"
    folder.mkdir(parents=True)
    (folder / "evaluation.json").write_text(json.dumps(record | {"dataset": {
        "dataset_id": "offdyn/hopper-gravity-0p5/medium-v0"}}))
    assert publish_reference_runs(tmp_path / "other-data", dest).written == (
        published / "medium-v0.seed-2" / "evaluation.json",)


def test_the_command_line_publishes_and_reports(sweep_out, tmp_path):
    from typer.testing import CliRunner

    from offdyn_bench.cli import app

    dest = tmp_path / "published"
    result = CliRunner().invoke(app, ["leaderboard", "publish-runs", str(sweep_out), "--to", str(dest)])
    assert result.exit_code == 0, result.output
    written = len(list(dest.rglob("*.json")))
    assert f"wrote {written} record(s) and 0 learning curve(s), 0 file(s) already published unchanged; 1 run(s) " \
        "of the sweep not evaluated yet" in result.output
    result = CliRunner().invoke(app, ["leaderboard", "publish-runs", str(tmp_path), "--to", str(dest)])
    assert result.exit_code == 2 and "no runs/ folder" in result.output


def test_the_leaderboard_shows_the_published_reference_runs_row_by_row(sweep_out, tmp_path):
    """Built twice from the same published runs: the same bytes, and one row per core task with the
    numbers `protocol gap` gives (and '-' where nothing is published yet)."""
    from leaderboard.render import build_site
    from offdyn_bench.protocol import CORE_SUITE
    from offdyn_bench.protocol.gap import measure_gaps

    published = tmp_path / "published"
    publish_reference_runs(sweep_out, published)
    store = tmp_path / "store"
    store.mkdir()
    first = build_site(store, tmp_path / "one", reference_runs=published)
    second = build_site(store, tmp_path / "two", reference_runs=published)
    assert [p.read_bytes() for p in first] == [p.read_bytes() for p in second]
    markdown = first[0].read_text()
    section = markdown[markdown.index("## Reference runs and the source-target gap (`lite`)"):]
    rows = {line.split(" | ")[0].strip("| "): line for line in section.splitlines() if line.startswith("| ")}
    assert set(CORE_SUITE) <= set(rows)
    records = [json.loads(p.read_text()) for p in sorted(published.glob("lite/sac-source/*/*/evaluation*.json"))]
    (gap,) = measure_gaps(records)
    oracle = [json.loads(p.read_text()) for p in sorted(published.glob("lite/sac-target/*/*/evaluation.json"))]
    oracle_means = [sum(r["seeds"][0]["returns"]) / len(r["seeds"][0]["returns"]) for r in oracle]
    # hopper-gravity-0.5's published P(oracle > RL on source) is 0.76: it fails the same-budget test.
    assert rows[gap.task] == (
        f"| {gap.task} | yes | fails | {gap.source_return:.1f} ({len(gap.source_seed_means)}) | "
        f"{gap.target_return:.1f} ({len(gap.target_seed_means)}) | {gap.kept:.2f} | "
        f"{sum(oracle_means) / len(oracle_means):.1f} ({len(oracle_means)}) | {gap.normalized_target:.1f} | "
        f"{gap.oracle_better_probability:.2f} |")
    assert gap.oracle_better_probability < 0.9
    assert rows["ant-friction-5.0"] == "| ant-friction-5.0 | yes | - | - | - | - | - | - | - |"
    page = first[1].read_text()
    assert '<table class="sortable" id="reference-runs-lite">' in page and "Reference runs and the source-target gap (lite)" in page
    # The page without them: no such section.
    bare = build_site(store, tmp_path / "bare")
    assert "Reference runs and the source-target gap" not in bare[0].read_text() + bare[1].read_text()


def test_the_leaderboard_shows_published_candidates_after_the_core_suite_with_their_test(sweep_out, tmp_path):
    """Runs of a pair outside the core suite are a candidate's: a row of their own after the core
    rows, marked so, with the same-budget test as far as the runs decide it (no oracle: undecided)."""
    from leaderboard.render import build_site
    from offdyn_bench.protocol import CORE_SUITE

    candidate = "hopper-gravity-5.0"
    assert candidate not in CORE_SUITE
    for path in sorted((sweep_out / "runs" / "sac-source" / "hopper-gravity-0.5").glob("*/evaluation*.json")):
        record = json.loads(path.read_text()) | {"task": candidate}
        moved = sweep_out / "runs" / "sac-source" / candidate / path.parent.name / path.name
        moved.parent.mkdir(parents=True, exist_ok=True)
        moved.write_text(json.dumps(record))
    published = tmp_path / "published"
    publish_reference_runs(sweep_out, published)
    store = tmp_path / "store"
    store.mkdir()
    markdown = build_site(store, tmp_path / "site", reference_runs=published)[0].read_text()
    section = markdown[markdown.index("## Reference runs and the source-target gap (`lite`)"):]
    tasks = [line.split(" | ")[0].strip("| ") for line in section.splitlines()
             if line.startswith("| ") and not line.startswith("| task ")]
    assert tasks == [*CORE_SUITE, candidate]
    rows = {line.split(" | ")[0].strip("| "): line.split(" | ")[1:] for line in section.splitlines()
            if line.startswith("| ")}
    # The same policies' returns as hopper-gravity-0.5's; no oracle runs and no oracle reference.
    assert rows[candidate] == ["candidate", "undecided", *rows["hopper-gravity-0.5"][2:5], "-", "-", "- |"]


def test_leaderboard_build_shows_the_repositorys_reference_runs_unless_told_not_to(tmp_path):
    from typer.testing import CliRunner

    from offdyn_bench.cli import app

    store = tmp_path / "store"
    store.mkdir()
    shown = CliRunner().invoke(app, ["leaderboard", "build", "--out", str(tmp_path / "a"), "--store", str(store)])
    assert shown.exit_code == 0, shown.output
    assert "## Reference runs and the source-target gap (`lite`)" in (tmp_path / "a" / "leaderboard.md").read_text()
    hidden = CliRunner().invoke(app, ["leaderboard", "build", "--out", str(tmp_path / "b"), "--store", str(store),
                                      "--no-reference-runs"])
    assert hidden.exit_code == 0, hidden.output
    assert "Reference runs and the source-target gap" not in (tmp_path / "b" / "leaderboard.md").read_text()


def test_the_leaderboard_refuses_published_runs_it_cannot_trust(sweep_out, tmp_path):
    from leaderboard.render import build_site

    store = tmp_path / "store"
    store.mkdir()
    with pytest.raises(SubmissionError, match=r"not a folder; expected published reference runs"):
        build_site(store, tmp_path / "site", reference_runs=tmp_path / "absent")
    published = tmp_path / "published"
    publish_reference_runs(sweep_out, published)
    edited = published / "lite" / "sac-target" / "hopper-gravity-0.5" / "seed-2" / "evaluation.json"
    record = json.loads(edited.read_text())
    del record["seeds"][0]["returns"][4:]
    edited.write_text(json.dumps(record))
    with pytest.raises(SubmissionError, match=r"seed-2/evaluation.json: seed 2: 4 episodes; the protocol scores "
                                              r"at least 20"):
        build_site(store, tmp_path / "site", reference_runs=published)
    assert not (tmp_path / "site").exists()


def _state(runs: dict) -> str:
    return json.dumps({"format": "offdyn-bench/sweep-state", "format_version": 1, "runs": runs})


def _attempt(number: int, wall: float, cpu: float) -> dict:
    return {"attempt": number, "ok": True, "stage": "check", "exit_code": None, "error": None,
            "wall_time_s": wall, "cpu_time_s": cpu, "host": "vm", "mean_return": 1.0}


def test_publishing_records_each_runs_compute_from_the_sweeps_state(sweep_out, tmp_path):
    done = {"status": "done", "attempts": 3, "wall_time_s": 1300.0, "cpu_time_s": 1250.0,
            "history": [_attempt(2, 100.0, 50.0),
                        _attempt(3, 1200.0, 1200.0) | {"started_at": "2026-11-29T06:24:26+00:00"}]}
    (sweep_out / "sweep.json").write_text(_state({
        "sac-target/hopper-gravity-0.5/seed-0": done,
        "sac-target/hopper-gravity-0.5/seed-9": {"status": "pending", "attempts": 1, "history": []}}))
    dest = tmp_path / "published"
    report = publish_reference_runs(sweep_out, dest)
    assert report.compute == (dest / "lite" / "compute.json",)
    compute = json.loads(report.compute[0].read_text())
    assert list(compute["runs"]) == ["sac-target/hopper-gravity-0.5/seed-0"]  # the published, finished run only
    entry = compute["runs"]["sac-target/hopper-gravity-0.5/seed-0"]
    assert entry["attempts_started"] == 3 and entry["wall_time_s"] == 1300.0 and entry["cpu_time_s"] == 1250.0
    assert [a["attempt"] for a in entry["recorded_attempts"]] == [2, 3]
    assert set(entry["recorded_attempts"][0]) == {"attempt", "ok", "stage", "started_at", "wall_time_s",
                                                  "cpu_time_s", "host"}
    # When each attempt started: CPU seconds from different days can differ. Unknown for a sweep
    # from before attempts recorded it.
    assert [a["started_at"] for a in entry["recorded_attempts"]] == [None, "2026-11-29T06:24:26+00:00"]
    # A later sweep state adds its runs and keeps the ones recorded before.
    (sweep_out / "sweep.json").write_text(_state({"sac-target/hopper-gravity-0.5/seed-1": done}))
    publish_reference_runs(sweep_out, dest)
    runs = json.loads(report.compute[0].read_text())["runs"]
    assert list(runs) == ["sac-target/hopper-gravity-0.5/seed-0", "sac-target/hopper-gravity-0.5/seed-1"]


def test_a_run_found_finished_keeps_the_compute_recorded_when_it_ran(sweep_out, tmp_path):
    # A later sweep that finds the records already there (restored from the published ones, or its
    # state file lost) measured nothing: the entry written when the run trained is kept.
    ran = {"status": "done", "attempts": 1, "wall_time_s": 1300.0, "cpu_time_s": 1250.0,
           "history": [_attempt(1, 1300.0, 1250.0)]}
    found = {"status": "done", "attempts": 0, "wall_time_s": 0.0, "cpu_time_s": 0.0, "history": []}
    run_id = "sac-target/hopper-gravity-0.5/seed-0"
    (sweep_out / "sweep.json").write_text(_state({run_id: ran}))
    dest = tmp_path / "published"
    publish_reference_runs(sweep_out, dest)
    compute_file = dest / "lite" / "compute.json"
    recorded = compute_file.read_bytes()
    (sweep_out / "sweep.json").write_text(_state({run_id: found}))
    publish_reference_runs(sweep_out, dest)
    assert compute_file.read_bytes() == recorded
    assert json.loads(recorded)["runs"][run_id]["cpu_time_s"] == 1250.0
    # Published for the first time with no compute measured: no entry rather than a false zero.
    (sweep_out / "sweep.json").write_text(_state({run_id: found}))
    report = publish_reference_runs(sweep_out, tmp_path / "fresh")
    assert report.compute == ()


def _write_result_compute(run: Path, compute: object) -> None:
    (run / "result.json").write_text(json.dumps({"algo": "sac-target", "compute": compute}))


def test_publishing_records_the_trainings_own_compute_over_all_its_attempts(sweep_out, tmp_path):
    runs = sweep_out / "runs" / "sac-target" / "hopper-gravity-0.5"
    training = {"wall_time_s": 1650.5, "cpu_time_s": 1601.25, "attempts": 3, "complete": True}
    _write_result_compute(runs / "seed-0", training)
    _write_result_compute(runs / "seed-1", {"wall_time_s": "long", "cpu_time_s": 1.0, "attempts": 1,
                                            "complete": True})  # not a time: left out, not guessed
    # The sweep saw only the last attempt: its state and the training's count sit side by side.
    (sweep_out / "sweep.json").write_text(_state({"sac-target/hopper-gravity-0.5/seed-0": {
        "status": "done", "attempts": 1, "wall_time_s": 700.0, "cpu_time_s": 690.0,
        "history": [_attempt(1, 700.0, 690.0)]}}))
    dest = tmp_path / "published"
    report = publish_reference_runs(sweep_out, dest)
    runs_compute = json.loads(report.compute[0].read_text())["runs"]
    entry = runs_compute["sac-target/hopper-gravity-0.5/seed-0"]
    assert entry["training"] == training and entry["wall_time_s"] == 700.0
    assert "sac-target/hopper-gravity-0.5/seed-1" not in runs_compute
    # Without a sweep state (runs trained by hand) the training's count is recorded alone, and it
    # is added to, not swapped for, an entry recorded earlier.
    (sweep_out / "sweep.json").unlink()
    training_two = training | {"attempts": 4}
    _write_result_compute(runs / "seed-0", training_two)
    publish_reference_runs(sweep_out, dest)
    entry = json.loads(report.compute[0].read_text())["runs"]["sac-target/hopper-gravity-0.5/seed-0"]
    assert entry["training"] == training_two and entry["recorded_attempts"][0]["wall_time_s"] == 700.0
    alone = publish_reference_runs(sweep_out, tmp_path / "by-hand")
    assert json.loads(alone.compute[0].read_text())["runs"] == {"sac-target/hopper-gravity-0.5/seed-0":
                                                                 {"training": training_two}}


def test_a_damaged_compute_file_publishes_nothing(sweep_out, tmp_path):
    _write_result_compute(sweep_out / "runs" / "sac-target" / "hopper-gravity-0.5" / "seed-0",
                          {"wall_time_s": 1.0, "cpu_time_s": 1.0, "attempts": 1, "complete": True})
    compute_file = tmp_path / "published" / "lite" / "compute.json"
    compute_file.parent.mkdir(parents=True)
    compute_file.write_text(json.dumps({"runs": {"sac-target/hopper-gravity-0.5/seed-0": [1, 2]}}))
    with pytest.raises(SubmissionError, match=r"compute.json: unreadable \(its runs are not a mapping of run "
                                              r"entries\); move it away"):
        publish_reference_runs(sweep_out, tmp_path / "published")
    assert [p.name for p in (tmp_path / "published").rglob("*") if p.is_file()] == ["compute.json"]


def test_a_broken_sweep_state_publishes_nothing(sweep_out, tmp_path):
    (sweep_out / "sweep.json").write_text('{"runs": [1, 2]}')
    with pytest.raises(SubmissionError, match=r"sweep.json: not a sweep state file \(its runs are not a mapping\); "
                                              r"nothing was published"):
        publish_reference_runs(sweep_out, tmp_path / "published")
    assert not (tmp_path / "published").exists()


def test_publishing_refuses_a_destination_under_a_file(sweep_out, tmp_path):
    blocker = tmp_path / "a-file"
    blocker.write_text("not a folder")
    with pytest.raises(SubmissionError, match=r"--to .*a-file/published: .*a-file is a file; expected a folder"):
        publish_reference_runs(sweep_out, blocker / "published")
    assert blocker.read_text() == "not a folder"


def _stored_reference_submissions() -> list[Path]:
    """The store's submissions of the reference points and of every method whose runs the
    repository publishes (MATL's, say): each is made from those runs."""
    from leaderboard.store import DEFAULT_STORE
    from offdyn_bench.protocol import REFERENCE_METHODS

    def published(path: Path) -> bool:
        method, _, budget = path.stem.split("__")
        return method in REFERENCE_METHODS or (REFERENCE_RUNS_DIR / budget / method).is_dir()

    return [path for path in sorted(DEFAULT_STORE.glob("*.json")) if published(path)]


@pytest.mark.parametrize("path", _stored_reference_submissions(), ids=lambda p: p.name)
def test_a_stored_reference_submission_is_what_its_published_runs_assemble_to(path):
    """No number of a reference method's submission is put in the store by hand: it is exactly
    `leaderboard submit leaderboard/reference-runs/<budget>/<method> --merge-seeds --core-suite-only`
    of the runs the repository publishes (its description aside; screened tasks published beside
    the core suite stay out of it)."""
    from leaderboard.assemble import assemble_submission

    stored = json.loads(path.read_text())
    method, track, budget = path.stem.split("__")
    assembled = assemble_submission(REFERENCE_RUNS_DIR / budget / method, method=method, track=track,
                                    merge_seeds=True, core_suite_only=True, description=stored["method"]["description"]).document
    assert stored == json.loads(json.dumps(assembled))



# The published claims, (claim, task, the target dataset's quality) -> ((seeds of the better side, of
# the worse), holds, the better side's return, the worse side's, P(better > worse)). "Better" is the
# side the paper says wins. The H2O rows are Table 1's `medium` cells.
_DOUBLES, _DAP_U = "dap >= 2x rl-on-source", "dap-u > dap"
_PUBLISHED_CLAIMS = {
    (_DOUBLES, "halfcheetah-friction-5.0", "source-policy"): ((5, 5), False, 1147.9, 979.6, 0.68),  # 1.17 times
    (_DOUBLES, "walker2d-morph-leg-medium", "source-policy"): ((5, 5), False, 470.6, 353.5, 0.80),  # 1.33 times
    (_DOUBLES, "hopper-gravity-0.5", "source-policy"): ((5, 5), False, 310.0, 477.8, 0.32),  # below it
    (_DOUBLES, "hopper-friction-0.5", "source-policy"): ((5, 5), False, 724.0, 523.9, 0.64),  # 1.38 times
    (_DOUBLES, "hopper-kinematic-foot-medium", "source-policy"): ((5, 5), False, 546.7, 468.4, 0.52),  # 1.17 times
    (_DOUBLES, "hopper-morph-thigh-medium", "source-policy"): ((5, 5), True, 1250.9, 495.7, 0.80),  # 2.52 times
    (_DOUBLES, "hopper-joint-noise-0.5", "source-policy"): ((5, 5), False, 667.7, 652.6, 0.56),  # 1.02 times
    (_DOUBLES, "walker2d-gravity-2.0", "source-policy"): ((5, 5), False, 258.4, 328.8, 0.16),  # 0.79 times
    (_DOUBLES, "walker2d-joint-noise-1.0", "source-policy"): ((5, 5), False, 139.6, 162.3, 0.32),  # 0.86 times
    (_DOUBLES, "halfcheetah-gravity-0.5", "source-policy"): ((5, 5), False, 2889.2, 3257.8, 0.40),  # 0.89 times
    (_DOUBLES, "halfcheetah-kinematic-bthigh-hard", "source-policy"): ((5, 5), False, 2789.3, 2851.5, 0.44),
    (_DOUBLES, "ant-friction-5.0", "source-policy"): ((5, 5), False, 6.8, 43.0, 0.0),  # its policies fall at once
    # RL on source's return is negative there: "doubles" has no verdict.
    (_DOUBLES, "ant-joint-noise-0.5", "source-policy"): ((5, 5), None, -149.8, -126.2, 0.40),
    (_DAP_U, "halfcheetah-friction-5.0", "source-policy"): ((5, 5), True, 1210.7, 1147.9, 0.68),
    (_DAP_U, "walker2d-morph-leg-medium", "source-policy"): ((5, 5), False, 421.2, 470.6, 0.32),  # below DAP there
    (_DAP_U, "walker2d-gravity-2.0", "source-policy"): ((5, 5), False, 236.0, 258.4, 0.28),
    # Five seeds (257.6, 198.3, 189.2, 245.4, 126.2); it read P 1.00 on two seeds and on four.
    (_DAP_U, "walker2d-joint-noise-1.0", "source-policy"): ((5, 5), True, 203.4, 139.6, 0.88),
    (_DAP_U, "hopper-gravity-0.5", "source-policy"): ((5, 5), True, 691.0, 310.0, 0.72),  # two seeds above the oracle
    (_DAP_U, "hopper-kinematic-foot-medium", "source-policy"): ((5, 5), True, 902.3, 546.7, 0.52),  # one seed carries it
    (_DAP_U, "hopper-friction-0.5", "source-policy"): ((5, 5), False, 623.4, 724.0, 0.52),  # held on seed 0
    # Five seeds (2781.4, 2456.1, 1336.1, 2109.4, 2217.5) against DAP's 2889.2.
    (_DAP_U, "halfcheetah-gravity-0.5", "source-policy"): ((5, 5), False, 2180.1, 2889.2, 0.16),
    # Five seeds (2857.5, 2624.8, 3129.0, 2749.1, 2889.5); it read P 0.80 on seed 0 and 0.60 on three.
    (_DAP_U, "halfcheetah-kinematic-bthigh-hard", "source-policy"): ((5, 5), True, 2850.0, 2789.3, 0.64),
    # Five seeds (-2.3, 2.8, 11.4, -9.9, 0.2); they fall at once, as DAP's do. It read P 0.33 on three.
    (_DAP_U, "ant-friction-5.0", "source-policy"): ((5, 5), False, 0.5, 6.8, 0.24),
    # Five seeds (-229.4, -312.1, -371.0, -145.1, -200.3), below DAP's five; every method's return is
    # negative on this pair, and "improves" needs no ratio, so it has a verdict. It read P 0.10 on
    # two seeds and 0.07 on three.
    (_DAP_U, "ant-joint-noise-0.5", "source-policy"): ((5, 5), False, -251.6, -149.8, 0.12),
    # Five seeds (807.9, 920.2, 828.0, 326.2, 830.0), the first published trainings that timed their
    # machine; it read P 0.90 on two seeds and 0.70 on four.
    (_DAP_U, "hopper-joint-noise-0.5", "source-policy"): ((5, 5), True, 742.4, 667.7, 0.76),
    # Split as DAP's seeds are (175.8, 900.8, 186.8; 1932.2, 1979.2): below DAP, but 2.09 times RL on source.
    (_DAP_U, "hopper-morph-thigh-medium", "source-policy"): ((5, 5), False, 1035.0, 1250.9, 0.32),
    ("h2o > darc", "halfcheetah-h2o-gravity-2.0", "medium"): ((5, 5), True, 2785.2, 2672.0, 0.68),  # DARC corrected
    ("h2o > darc", "halfcheetah-h2o-friction-0.3", "medium"): ((5, 5), True, 3746.9, 2790.3, 1.0),  # DARC corrected
    ("h2o > darc", "halfcheetah-h2o-joint-noise-1.0", "medium"): ((5, 5), True, 3155.8, 1378.2, 1.0),  # DARC corrected
    ("h2o > cql", "halfcheetah-h2o-gravity-2.0", "medium"): ((5, 1), True, 2785.2, 2764.8, 0.80),  # one CQL seed so far
    # Outside the H2O paper's settings: shown, and not counted where the paper claims it.
    ("h2o > darc", "hopper-gravity-0.5", "source-policy"): ((5, 5), True, 841.1, 312.8, 0.88),  # DARC corrected
    ("h2o > cql", "hopper-gravity-0.5", "source-policy"): ((5, 5), True, 841.1, 502.3, 0.72),
    # Five seeds each: H2O 15.2 above DARC on the means, 24.9 below CQL's.
    ("h2o > darc", "hopper-kinematic-foot-medium", "source-policy"): ((5, 5), True, 555.2, 540.0, 0.56),
    ("h2o > cql", "hopper-kinematic-foot-medium", "source-policy"): ((5, 5), False, 555.2, 580.1, 0.40),
    ("h2o > darc", "hopper-friction-0.5", "source-policy"): ((5, 5), True, 737.6, 597.3, 0.60),
    # Above CQL on the means by 30.9, yet CQL's seeds (681.7 to 735.0) sit tighter: P 0.40.
    ("h2o > cql", "hopper-friction-0.5", "source-policy"): ((5, 5), True, 737.6, 706.7, 0.40),
    # Five seeds on morph-thigh (it held on seed 0 alone).
    ("h2o > darc", "hopper-morph-thigh-medium", "source-policy"): ((5, 5), False, 544.2, 836.5, 0.36),
    ("h2o > cql", "hopper-morph-thigh-medium", "source-policy"): ((5, 5), True, 544.2, 250.3, 0.68),
    # Five seeds on joint noise: 117.6 above DARC on the means (P 0.90 on two seeds, 0.55 on four).
    ("h2o > darc", "hopper-joint-noise-0.5", "source-policy"): ((5, 5), True, 862.1, 744.5, 0.64),
    # CQL's five seeds there, trained on this machine's CPU (953.4, 864.2, 961.2, 974.4 and 940.0;
    # oracle 791.6).
    ("h2o > cql", "hopper-joint-noise-0.5", "source-policy"): ((5, 5), False, 862.1, 938.7, 0.44),
    # H2O's five Walker2d seeds (-53.7, -34.7, 122.3, 158.2, 127.2), their critics' values running
    # away (PROTOCOL §9); it read 23.3 on three seeds.
    ("h2o > darc", "walker2d-gravity-2.0", "source-policy"): ((5, 5), False, 63.9, 246.5, 0.0),
    # HalfCheetah's core gravity pair, five seeds each: H2O 832.7, 895.3, 793.8, 957.6, 472.9 against
    # DARC 3,094.8, 2,787.7, 2,712.1, 1,589.5, 3,600.3 (PROTOCOL §9); it read 832.7 against 3,094.8 on seed 0.
    ("h2o > darc", "halfcheetah-gravity-0.5", "source-policy"): ((5, 5), False, 790.4, 2756.9, 0.0),
    # CQL's four seeds there (this machine's CPU): 1,692.1, 2,804.2, 2,512.8 and 2,008.5, above every
    # H2O seed.
    ("h2o > cql", "halfcheetah-gravity-0.5", "source-policy"): ((5, 4), False, 790.4, 2254.4, 0.0),
    # HalfCheetah under friction, five seeds each: H2O 765.2, 1,977.5, 1,377.3, 1,084.1, 1,471.3 against
    # DARC 658.3, 1,633.1, 1,229.0, 1,076.5, 1,046.5 (PROTOCOL §9); it read P 1.00 on seed 0 and 0.62 on four.
    ("h2o > darc", "halfcheetah-friction-5.0", "source-policy"): ((5, 5), True, 1335.1, 1128.7, 0.68),  # 17 of 25 pairs
    # HalfCheetah's back thigh, five seeds each: H2O 1,439.3, 929.5, 1,242.5, 1,772.4, 1,381.6 against
    # DARC 3,035.0, 2,785.2, 3,421.5, 3,305.3, 3,061.7 (PROTOCOL §9): every seed pair goes to DARC.
    ("h2o > darc", "halfcheetah-kinematic-bthigh-hard", "source-policy"): ((5, 5), False, 1353.1, 3121.8, 0.0),
    # Walker2d's leg-morphology pair, five seeds each: H2O 134.3, 191.8, 176.4, 140.4, 172.0 against DARC
    # 209.6, 205.0, 541.5, 246.5, 197.3; H2O's critic runs away on every seed (PROTOCOL §9).
    ("h2o > darc", "walker2d-morph-leg-medium", "source-policy"): ((5, 5), False, 163.0, 280.0, 0.0),
    # Walker2d under joint noise, five seeds each: H2O 169.4, 86.0, 67.7, 122.5, 201.9 against DARC 137.1,
    # 118.0, 152.5, 196.7, 162.7 (PROTOCOL §9); it held by 0.1 on two seeds (P 0.50), not on four (0.25).
    ("h2o > darc", "walker2d-joint-noise-1.0", "source-policy"): ((5, 5), False, 129.5, 153.4, 0.40),
    # Ant under friction, five seeds each: H2O 11.5, 5.0, 1.8, 5.9, 3.0 against DARC -0.8, 0.6, 1.1,
    # 6.7, -0.8 (PROTOCOL §9). Both methods' policies fall at once there, far below RL on source's 43.0:
    # a verdict between two failures. It read P 1.00 on three seeds.
    ("h2o > darc", "ant-friction-5.0", "source-policy"): ((5, 5), True, 5.5, 1.3, 0.84),
    # Ant under joint noise, five seeds each: H2O -321.8, -439.5, -183.2, -61.3, -326.7 against DARC
    # -148.0, -202.8, -140.0, -335.1, -117.2 (PROTOCOL §9); it read P 0.00 on two seeds, 0.44 on four.
    ("h2o > darc", "ant-joint-noise-0.5", "source-policy"): ((5, 5), False, -266.5, -188.6, 0.36),
}
# The H2O paper claims its rows on Table 1's HalfCheetah settings only; every other H2O row is "not
# claimed here", so a newly published pair needs no entry.
_H2O_CLAIMED_TASKS = ("halfcheetah-h2o-gravity-2.0", "halfcheetah-h2o-friction-0.3", "halfcheetah-h2o-joint-noise-1.0")


def test_the_boards_claims_are_protocol_claims_on_the_published_runs(tmp_path):
    """The board checks the papers' claims on every published target record, as `protocol claims`
    does: DAP on halfcheetah-friction-5.0 returns 1147.9 against RL on source's 979.6 over 5 seeds
    each, 1.17x, so "DAP at least doubles RL on source" does not hold there at lite; DAP+U's 1210.7
    is above DAP's, with P 0.68, and on walker2d-morph-leg-medium DAP+U's 421.2 is below DAP's
    470.6 (P 0.32), so "DAP+U improves on DAP" holds on one passing pair and not the other."""
    from leaderboard.reference_runs import reference_claims
    from leaderboard.render import build_site
    from offdyn_bench.datasets.recipes import dataset_id
    from offdyn_bench.protocol.claims import check_claims

    lite = [json.loads(path.read_text()) for path in PUBLISHED
            if _parts(path)[0] == "lite" and path.name == "evaluation.json"]
    board = reference_claims()["lite"]
    assert [check.to_dict() for check in board] == [check.to_dict() for check in check_claims(lite)]
    # The table pins every row the board shows, so a row on another dataset (an H2O row outside
    # Table 1's `medium` cells, say) fails here instead of going unchecked.
    assert sorted((c.claim.name, c.task, c.dataset) for c in board) == sorted(
        (name, task, dataset_id(task, quality)) for name, task, quality in _PUBLISHED_CLAIMS)
    for (name, task, quality), expected in _PUBLISHED_CLAIMS.items():
        (check,) = [c for c in board if (c.claim.name, c.task, c.dataset) == (name, task, dataset_id(task, quality))]
        seeds, holds, better, worse, probability = expected
        assert ((check.better_seeds, check.worse_seeds), check.holds) == (seeds, holds), (name, task)
        assert check.better_return == pytest.approx(better, abs=0.05), (name, task)
        assert check.worse_return == pytest.approx(worse, abs=0.05), (name, task)
        # Rounded to the two decimals the board prints; 1.0 (every seed above every seed) exactly.
        assert check.probability_of_improvement == (
            probability if probability == 1.0 else pytest.approx(probability, abs=0.005)), (name, task)
        assert check.claimed_on_task == (not name.startswith("h2o") or task in _H2O_CLAIMED_TASKS), (name, task)
        # Every published DARC run applies its correction from step 10,000 (PROTOCOL §9, decision 5),
        # so no verdict is against a training too short for what it claims.
        assert check.caveats == (), (name, task)
    store = tmp_path / "store"
    store.mkdir()
    markdown, page = build_site(store, tmp_path / "site", reference_runs=REFERENCE_RUNS_DIR)
    assert ("| dap >= 2x rl-on-source | DAP, Section 5.2 | halfcheetah-friction-5.0 | "
            "offdyn/halfcheetah-friction-5p0/source-policy-v0 | dap: 1147.9 (5) | sac-source: 979.6 (5) | "
            "does not hold | 0.68 |") in markdown.read_text()
    assert 'id="reference-claims-lite"' in page.read_text()


def test_the_board_marks_a_verdict_against_darc_runs_that_never_applied_their_correction(tmp_path):
    """No published DARC run is the published schedule's any more, so the board's caveat is checked
    on a copy of the H2O gravity cell whose DARC train commands are rewritten to that schedule: at
    lite its correction would start at step 100,000, the end of the run, and the verdict says so in
    both the markdown and the page."""
    from leaderboard.render import build_site

    published = tmp_path / "published"
    for method in ("h2o", "darc"):
        cell = Path("lite", method, "halfcheetah-h2o-gravity-2.0")
        shutil.copytree(REFERENCE_RUNS_DIR / cell, published / cell)
    darc_records = sorted((published / "lite" / "darc").glob("*/medium-v0.seed-*/evaluation.json"))
    assert len(darc_records) == 5
    for path in darc_records:
        record = json.loads(path.read_text())
        assert " --set warmup_steps=10000" in record["train_command"]
        record["train_command"] = re.sub(r" --set \S+", "", record["train_command"])
        path.write_text(json.dumps(record))
    store = tmp_path / "store"
    store.mkdir()
    markdown, page = build_site(store, tmp_path / "site", reference_runs=published)
    caveat = ("holds (caveat: darc: --steps 100000 is not above warmup_steps=100000: this darc run never applies "
              "its reward correction and trains plain SAC)")
    board = markdown.read_text()
    assert "| halfcheetah-h2o-gravity-2.0 | offdyn/halfcheetah-h2o-gravity-2p0/medium-v0 |" in board
    assert caveat in board
    assert caveat in page.read_text()


def test_the_boards_claims_refuse_a_hand_edited_record(tmp_path):
    from leaderboard.reference_runs import reference_claims

    published = tmp_path / "published"
    shutil.copytree(REFERENCE_RUNS_DIR / "lite" / "dap", published / "lite" / "dap")
    shutil.copytree(REFERENCE_RUNS_DIR / "lite" / "sac-source", published / "lite" / "sac-source")
    assert reference_claims(published)["lite"]
    edited = published / "lite" / "dap" / "halfcheetah-friction-5.0" / "seed-1" / "evaluation.json"
    record = json.loads(edited.read_text())
    record["method"] = "dap-u"  # claimed as another method's run
    edited.write_text(json.dumps(record))
    with pytest.raises(SubmissionError, match=r"holds 'dap-u' on 'halfcheetah-friction-5.0', but its folder names 'dap'"):
        reference_claims(published)
    (tmp_path / "nothing").mkdir()
    assert reference_claims(tmp_path / "nothing") == {}  # no budget published: no claims section


def test_a_folder_that_names_a_dataset_must_hold_a_record_trained_on_it(tmp_path):
    """A ``datasets`` sweep names each run's dataset in its folder (``medium-v0.seed-0``): publishing
    takes that name at its word only where the record trained on that dataset."""
    dap = REFERENCE_RUNS_DIR / "lite" / "dap" / "halfcheetah-friction-5.0" / "seed-0" / "evaluation.json"
    record = json.loads(dap.read_text())
    assert record["dataset"]["dataset_id"] == "offdyn/halfcheetah-friction-5p0/source-policy-v0"
    check_reference_record(dap, record, "dap", "halfcheetah-friction-5.0", "source-policy-v0.seed-0", "target")
    with pytest.raises(SubmissionError, match=r"trained on dataset 'offdyn/halfcheetah-friction-5p0/source-policy-v0'; "
                                              r"its folder 'medium-v0.seed-0' names 'medium-v0'"):
        check_reference_record(dap, record, "dap", "halfcheetah-friction-5.0", "medium-v0.seed-0", "target")
    with pytest.raises(SubmissionError, match=r"seeds \[0\]; its folder 'source-policy-v0.seed-1' names others"):
        check_reference_record(dap, record, "dap", "halfcheetah-friction-5.0", "source-policy-v0.seed-1", "target")
    rl = REFERENCE_RUNS_DIR / "lite" / "sac-source" / "halfcheetah-friction-5.0" / "seed-0" / "evaluation.json"
    with pytest.raises(SubmissionError,
                       match=r"trained on no target dataset; its folder 'medium-v0.seed-0' names 'medium-v0'"):
        check_reference_record(rl, json.loads(rl.read_text()), "sac-source", "halfcheetah-friction-5.0",
                               "medium-v0.seed-0", "target")


def test_protocol_md_matl_numbers_are_the_published_runs():
    """PROTOCOL.md §9's MATL bullet, recomputed as `protocol score` computes it from the published
    MATL records and RL on source's target records on the same tasks."""
    from offdyn_bench.protocol.report import score_report

    from offdyn_bench.protocol import CORE_SUITE

    matl = _records("matl", name="evaluation.json")
    tasks = {record["task"] for record in matl}
    assert tasks == set(CORE_SUITE) and len(matl) == 5 * len(CORE_SUITE)
    source = [record for record in _records("sac-source", name="evaluation.json") if record["task"] in tasks]
    report = score_report(matl + source)
    by_method = {scores.method: scores for scores in report.methods}
    ant = report.tasks.index("ant-friction-5.0")
    assert by_method["matl"].raw[:, ant].mean() == pytest.approx(727.1, abs=0.05)
    assert by_method["matl"].normalized[:, ant].mean() == pytest.approx(394.2, abs=0.05)
    assert report.aggregates["matl"]["iqm"].point == pytest.approx(16.0, abs=0.05)
    assert report.aggregates["sac-source"]["iqm"].point == pytest.approx(53.9, abs=0.05)
    assert report.improvement["matl>sac-source"].point == pytest.approx(0.22, abs=0.005)
    assert by_method["matl"].normalized.mean() == pytest.approx(52.5, abs=0.05)
