"""The offdyn-bench leaderboard: submission schema and validation, the canonical store, the
rendered board (markdown and HTML) and the submission server.

Nothing heavy is imported here (the CLI imports this package to start); the public names load
their module on first use.
"""

from __future__ import annotations

import importlib
from typing import Any

_PUBLIC = {
    "Submission": "leaderboard.submission",
    "SubmissionError": "leaderboard.submission",
    "validate_submission": "leaderboard.submission",
    "read_submission_file": "leaderboard.submission",
    "parse_json_strict": "leaderboard.submission",
    "SCHEMA_PATH": "leaderboard.submission",
    "assemble_submission": "leaderboard.assemble",
    "DEFAULT_STORE": "leaderboard.store",
    "DuplicateSubmissionError": "leaderboard.store",
    "load_store": "leaderboard.store",
    "write_submission": "leaderboard.store",
    "Board": "leaderboard.scores",
    "score_board": "leaderboard.scores",
    "render_markdown": "leaderboard.render",
    "render_html": "leaderboard.render",
    "build_site": "leaderboard.render",
    "create_app": "leaderboard.server",
    "Database": "leaderboard.database",
}

__all__ = sorted(_PUBLIC)


def __getattr__(name: str) -> Any:
    if name not in _PUBLIC:
        raise AttributeError(f"module 'leaderboard' has no attribute {name!r}")
    return getattr(importlib.import_module(_PUBLIC[name]), name)
