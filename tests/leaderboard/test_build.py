"""``leaderboard build``: scores recomputed from raw returns, hand-checked; same store, same bytes."""

from __future__ import annotations

import base64
import json
import re
from pathlib import Path

import pytest
from typer.testing import CliRunner

from leaderboard.cli import leaderboard_app
from leaderboard.render import build_site, render_markdown
from leaderboard.scores import score_board
from leaderboard.store import DuplicateSubmissionError, load_store, write_submission
from leaderboard.submission import SubmissionError, canonical_json, validate_submission


@pytest.fixture
def store(tmp_path: Path, make_submission) -> Path:
    """alpha (the hand-computed one), beta (better), gamma on the online track, all at budget lite."""
    store = tmp_path / "store"
    write_submission(store, validate_submission(make_submission("alpha", curves=True)))
    beta = {"hopper-gravity-0.5": (50.0, 60.0, 70.0), "walker2d-gravity-2.0": (110.0, 130.0, 150.0),
            "ant-gravity-0.1": (400.0, 410.0, 420.0)}
    write_submission(store, validate_submission(make_submission("beta", seed_means=beta)))
    write_submission(store, validate_submission(make_submission("gamma", track="online-target")))
    return store


def test_scores_match_hand_computed_values(store: Path, references_file: Path) -> None:
    board = score_board(load_store(store), references=references_file)
    normalization = board.normalizations["lite"]
    assert normalization.scored_tasks == ("hopper-gravity-0.5", "walker2d-gravity-2.0")
    assert list(normalization.excluded) == ["ant-gravity-0.1"]
    assert "no oracle/lite reference" in normalization.excluded["ant-gravity-0.1"]

    by_method = {e.submission.method: e for e in board.entries}
    alpha = by_method["alpha"]
    # hopper 10 20 30 and walker (50-10)/2 .. = 20 40 60: pooled 10 20 20 30 40 60.
    assert alpha.normalized.tolist() == [[10.0, 20.0], [20.0, 40.0], [30.0, 60.0]]
    assert alpha.iqm.point == pytest.approx(27.5)
    assert alpha.mean.point == pytest.approx(30.0)
    assert alpha.optimality_gap.point == pytest.approx(70.0)
    assert alpha.iqm.low <= alpha.iqm.point <= alpha.iqm.high
    assert alpha.raw_mean == {"hopper-gravity-0.5": 20.0, "walker2d-gravity-2.0": 90.0, "ant-gravity-0.1": 200.0}
    # beta: hopper 50 60 70, walker 50 60 70: pooled 50 50 60 60 70 70 -> IQM 60, gap 40.
    assert by_method["beta"].iqm.point == pytest.approx(60.0)
    assert by_method["beta"].optimality_gap.point == pytest.approx(40.0)
    # P(beta > alpha): hopper 50..70 beat 10..30 in all 9 pairs; walker 50 60 70 against 20 40 60
    # wins 2 + (2 + 1/2 tie) + 3 = 7.5 of 9 pairs: mean (1 + 7.5/9) / 2 = 11/12.
    improvements = {(i.x, i.y): i.probability.point for i in board.improvements}
    assert improvements == pytest.approx({("beta", "alpha"): 11 / 12, ("alpha", "beta"): 1 / 12})
    # Order: track, budget, IQM highest first.
    assert [e.submission.method for e in board.entries] == ["beta", "alpha", "gamma"]


def test_markdown_table_shows_recomputed_scores_and_exclusions(store: Path, references_file: Path,
                                                              tmp_path: Path) -> None:
    markdown = render_markdown(score_board(load_store(store), references=references_file))
    rows = [line for line in markdown.splitlines() if line.startswith("| ")]
    assert rows[0].split(" | ")[-3:] == ["hopper-gravity-0.5", "walker2d-gravity-2.0", "ant-gravity-0.1 |"]
    alpha = next(row for row in rows if row.startswith("| alpha "))
    cells = [c.strip() for c in alpha.strip("|").split("|")]
    assert cells[:4] == ["alpha", "offline-target", "lite", "3"]
    assert re.fullmatch(r"27\.5 \[[\d.]+, [\d.]+\]", cells[4])
    assert cells[5].startswith("30.0 [") and cells[6].startswith("70.0 [")
    assert cells[7:] == ["20.0", "90.0", "200.0"]
    assert "Excluded from the `lite` normalized scores: `ant-gravity-0.1`" in markdown
    assert "over 2 of 3 core tasks" in markdown


def test_a_task_whose_oracle_the_zero_command_beats_is_flagged_not_rescored(store: Path, references_file: Path,
                                                                           tmp_path: Path) -> None:
    """protocol 1.0's Ant pairs: an oracle below what commanding nothing earns. The board keeps the
    version's scores (a protocol change would be a new version) and says what they measure."""
    data = json.loads(references_file.read_text())
    plain = render_markdown(score_board(load_store(store), references=references_file))
    # walker2d-gravity-2.0: random 10, oracle 210; the zero command earns 250 there.
    data["tasks"]["walker2d-gravity-2.0"]["zero_command"] = {"mean_return": 250.0, "returns": [250.0],
                                                              "provenance": {}}
    data["tasks"]["hopper-gravity-0.5"]["zero_command"] = {"mean_return": 5.0, "returns": [5.0], "provenance": {}}
    references_file.write_text(json.dumps(data))
    board = score_board(load_store(store), references=references_file)
    assert dict(board.normalizations["lite"].below_zero_command) == {"walker2d-gravity-2.0": (250.0, 120.0)}
    markdown = render_markdown(board)
    assert ("Oracle below the zero command, budget `lite`: `walker2d-gravity-2.0`: the policy that commands nothing "
            "earns 250.0, the oracle 210.0, so doing nothing scores 120 normalized") in markdown
    assert "`hopper-gravity-0.5`: the policy that commands nothing" not in markdown
    _, page_path = build_site(store, tmp_path / "site", references=references_file)
    assert ("Oracle below the zero command at <code>lite</code>: <code>walker2d-gravity-2.0</code>: the policy that "
            "commands nothing earns 250.0") in page_path.read_text()
    # Every score is as before: only the note is new.
    assert [line for line in markdown.splitlines() if line.startswith("| ")] == \
        [line for line in plain.splitlines() if line.startswith("| ")]


def test_html_page_holds_table_breakdown_plots_and_exclusions(store: Path, references_file: Path,
                                                             tmp_path: Path) -> None:
    _, page_path = build_site(store, tmp_path / "site", references=references_file)
    page = page_path.read_text()
    assert '<table class="sortable" id="leaderboard">' in page and 'id="per-task"' in page
    assert "27.5 [" in page and "P(row &gt; column)" in page
    assert "Excluded at <code>lite</code>: <code>ant-gravity-0.1</code>" in page
    images = re.findall(r'src="data:image/png;base64,([^"]+)"', page)
    assert len(images) == 3  # profiles of offline-target/lite and online-target/lite, learning curves
    for image in images:
        assert base64.b64decode(image).startswith(b"\x89PNG\r\n\x1a\n")
    assert "http" not in re.sub(r'href="https://example\.org/code"', "", page).replace(
        "https://json-schema", "")  # self-contained: nothing is fetched


def test_same_store_same_bytes(store: Path, references_file: Path, tmp_path: Path, make_submission) -> None:
    first = build_site(store, tmp_path / "one", references=references_file)
    # A copy of the store written in another order renders identically.
    copy = tmp_path / "copy"
    for path in sorted(store.glob("*.json"), reverse=True):
        write_submission(copy, validate_submission(json.loads(path.read_text())))
    second = build_site(copy, tmp_path / "two", references=references_file)
    for a, b in zip(first, second):
        assert a.read_bytes() == b.read_bytes()


def test_user_text_is_escaped(tmp_path: Path, references_file: Path, make_submission) -> None:
    document = make_submission("delta")
    document["method"]["description"] = '<script>alert("x")</script> | pipe'
    store = tmp_path / "store"
    write_submission(store, validate_submission(document))
    markdown_path, page_path = build_site(store, tmp_path / "site", references=references_file)
    assert "<script>alert" not in page_path.read_text()
    assert "&lt;script&gt;alert" in page_path.read_text()


def test_board_without_any_oracle_shows_raw_returns(tmp_path: Path, make_submission) -> None:
    store = tmp_path / "store"
    write_submission(store, validate_submission(make_submission("alpha")))
    empty_references = tmp_path / "none.json"  # missing file: no reference at all
    markdown_path, page_path = build_site(store, tmp_path / "site", references=empty_references)
    markdown = markdown_path.read_text()
    assert "| alpha | offline-target | lite | 3 | n/a | n/a | n/a | 20.0 | 90.0 | 200.0 |" in markdown
    assert "none yet" in markdown
    assert "No entry has normalized scores yet" in page_path.read_text()


def test_store_refuses_duplicates_and_misnamed_files(tmp_path: Path, make_submission) -> None:
    store = tmp_path / "store"
    submission = validate_submission(make_submission("alpha"))
    path = write_submission(store, submission)
    before = path.read_bytes()
    assert before == canonical_json(submission.document)
    with pytest.raises(DuplicateSubmissionError, match="already holds alpha on the offline-target track"):
        write_submission(store, submission)
    assert path.read_bytes() == before and sorted(p.name for p in store.iterdir()) == [path.name]
    path.rename(store / "renamed.json")
    with pytest.raises(SubmissionError, match="its name must be alpha__offline-target__lite.json"):
        load_store(store)


def test_a_failed_write_leaves_nothing(tmp_path: Path, make_submission, monkeypatch: pytest.MonkeyPatch) -> None:
    import os

    store = tmp_path / "store"
    store.mkdir()

    def broken_replace(source: str, target: str) -> None:
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(os, "replace", broken_replace)
    with pytest.raises(OSError):
        write_submission(store, validate_submission(make_submission("alpha")))
    assert list(store.iterdir()) == []


def test_build_command(store: Path, references_file: Path, tmp_path: Path) -> None:
    runner = CliRunner()
    result = runner.invoke(leaderboard_app, ["build", "--store", str(store), "--out", str(tmp_path / "site"),
                                             "--references", str(references_file)])
    assert result.exit_code == 0, result.output
    assert (tmp_path / "site" / "index.html").is_file() and (tmp_path / "site" / "leaderboard.md").is_file()
    (store / "broken.json").write_text("{")
    result = runner.invoke(leaderboard_app, ["build", "--store", str(store), "--out", str(tmp_path / "other")])
    assert result.exit_code == 2
    assert "error:" in result.output and "broken.json: not valid JSON" in result.output
    assert not (tmp_path / "other").exists()


def test_build_into_an_unwritable_place_is_a_clear_error(store: Path, references_file: Path, tmp_path: Path) -> None:
    blocker = tmp_path / "a-file"
    blocker.write_text("not a folder")
    result = CliRunner().invoke(leaderboard_app, ["build", "--store", str(store), "--out", str(blocker / "site"),
                                                  "--references", str(references_file)])
    assert result.exit_code == 2 and "Traceback" not in result.output
    assert f"--out '{blocker / 'site'}': cannot write the leaderboard there" in result.output
    assert blocker.read_text() == "not a folder"


@pytest.mark.parametrize("args, message", [(["--port", "99999"], "--port 99999: expected a TCP port in \\[0, 65535\\]"),
                                           (["--max-body-bytes", "0"], "--max-body-bytes 0: expected a positive")])
def test_serve_refuses_bad_options_before_opening_anything(tmp_path: Path, args: list[str], message: str) -> None:
    import re

    db = tmp_path / "board.sqlite3"
    result = CliRunner().invoke(leaderboard_app, ["serve", "--db", f"sqlite:///{db}", *args])
    assert result.exit_code == 2 and re.search("error: " + message, result.output), result.output
    assert not db.exists()


def test_curves_for_some_tasks_only_plot_without_warnings(tmp_path: Path, references_file: Path,
                                                          make_submission) -> None:
    # RL on source submits curves only for the tasks it trained on: the first task of the board
    # may have none, and its frame says so instead of carrying a legend with nothing in it.
    import warnings

    from leaderboard.render import _learning_curve_plot

    document = make_submission("alpha", curves=True)
    del document["tasks"]["hopper-gravity-0.5"]["learning_curve"]
    store = tmp_path / "store"
    write_submission(store, validate_submission(document))
    board = score_board(load_store(store), references=references_file)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        image = _learning_curve_plot(board)
    assert image is not None and base64.b64decode(image).startswith(b"\x89PNG")
