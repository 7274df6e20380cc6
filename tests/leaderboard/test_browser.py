"""The rendered page in a real browser: Debian's chromium, headless, driven by Playwright.

Skips (with the reason) only where the browser cannot be had: no playwright package, no
/usr/bin/chromium (``.ci/run`` installs both), or a chromium that does not start.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from leaderboard.render import build_site
from leaderboard.store import write_submission
from leaderboard.submission import validate_submission

CHROMIUM = "/usr/bin/chromium"
CHROMIUM_FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--no-first-run", "--disable-background-networking",
                  "--disable-component-update", "--disable-sync"]


@pytest.fixture
def page_file(tmp_path: Path, make_submission, references_file: Path) -> Path:
    """Three methods whose order differs by IQM, by name and by raw hopper return."""
    store = tmp_path / "store"
    means = {
        "alpha": (10.0, 20.0, 30.0),   # IQM 27.5, hopper raw 20
        "beta": (50.0, 60.0, 70.0),    # IQM 60, hopper raw 60
        "gamma": (0.0, 5.0, 10.0),     # lowest, hopper raw 5
    }
    for method, hopper in means.items():
        walker = tuple(10.0 + 2 * m for m in hopper)  # the same normalized score as hopper
        write_submission(store, validate_submission(make_submission(method, seed_means={
            "hopper-gravity-0.5": hopper, "walker2d-gravity-2.0": walker, "ant-gravity-0.1": (1.0, 2.0, 3.0)})))
    _, page = build_site(store, tmp_path / "site", references=references_file)
    return page


def _browser_context(playwright, profile: Path):
    try:
        return playwright.chromium.launch_persistent_context(
            str(profile), executable_path=CHROMIUM, headless=True, args=CHROMIUM_FLAGS,
            viewport={"width": 1400, "height": 900})
    except Exception as error:  # noqa: BLE001 - any launch failure means "no usable browser here"
        pytest.skip(f"chromium at {CHROMIUM} does not start under Playwright: {str(error).splitlines()[0]}")


def test_table_renders_and_sorts_on_header_click(page_file: Path, tmp_path: Path) -> None:
    sync_api = pytest.importorskip("playwright.sync_api", reason="playwright not installed (pip install -e '.[test]')")
    if shutil.which(CHROMIUM) is None:
        pytest.skip(f"no {CHROMIUM}: install Debian's chromium (apt-get install -y chromium; .ci/run does it)")

    with sync_api.sync_playwright() as playwright:
        context = _browser_context(playwright, tmp_path / "chromium-profile")
        try:
            page = context.new_page()
            page.goto(page_file.as_uri())
            table = page.locator("#leaderboard")
            assert table.is_visible()

            screenshot = tmp_path / "board.png"
            page.screenshot(path=str(screenshot), full_page=True)
            data = screenshot.read_bytes()
            assert data.startswith(b"\x89PNG\r\n\x1a\n") and len(data) > 10_000

            def methods() -> list[str]:
                return page.eval_on_selector_all("#leaderboard tbody tr td:first-child",
                                                 "cells => cells.map(c => c.dataset.sort)")

            assert methods() == ["beta", "alpha", "gamma"]  # the board's order: IQM, highest first
            header = table.locator("thead th", has_text="method")
            header.click()
            assert methods() == ["alpha", "beta", "gamma"]
            assert header.get_attribute("aria-sort") == "ascending"
            header.click()
            assert methods() == ["gamma", "beta", "alpha"]
            # Numeric columns sort by value, not text: raw hopper returns 5, 20, 60.
            table.locator("thead th", has_text="hopper-gravity-0.5").click()
            assert methods() == ["gamma", "alpha", "beta"]
            table.locator("thead th", has_text="IQM").click()
            assert methods() == ["gamma", "alpha", "beta"]
            table.locator("thead th", has_text="IQM").click()
            assert methods() == ["beta", "alpha", "gamma"]
        finally:
            context.close()
