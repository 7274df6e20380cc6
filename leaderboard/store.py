"""The canonical store: one JSON file per accepted submission, ``<method>__<track>__<budget>.json``.

The repository's ``leaderboard/submissions/`` is the board of record; ``build`` renders it and
``serve`` appends to it. Files are written atomically (temporary file, fsync, ``os.replace``), so a
reader never sees half a submission.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

from leaderboard.submission import Submission, SubmissionError, canonical_json, read_submission_file

DEFAULT_STORE = Path(__file__).resolve().parent / "submissions"


class DuplicateSubmissionError(SubmissionError):
    """The store already holds an entry for this method, track and budget."""


def store_path(store: Path, submission: Submission) -> Path:
    """Where ``submission`` lives in ``store``; refuses any name that would resolve elsewhere."""
    root = store.resolve()
    path = (root / submission.file_name).resolve()
    # The schema already restricts method names; this guards the invariant independently of it.
    if path.parent != root or not path.name.endswith(".json"):
        raise SubmissionError(f"method name {submission.method!r} does not name a file inside the store {root}")
    return path


def load_store(store: Path) -> list[Submission]:
    """Every submission of ``store``, validated, in file-name order. Raises on the first bad file."""
    if not store.is_dir():
        raise SubmissionError(f"submission store {store} is not a directory; expected a folder of "
                              "<method>__<track>__<budget>.json files")
    submissions = []
    for path in sorted(store.glob("*.json")):
        submission = read_submission_file(path)
        if path.name != submission.file_name:
            raise SubmissionError(f"{path}: holds {submission.method} on {submission.track}/{submission.budget}, "
                                  f"so its name must be {submission.file_name}")
        submissions.append(submission)
    return submissions


def write_submission(store: Path, submission: Submission) -> Path:
    """Add ``submission`` to ``store`` atomically; :class:`DuplicateSubmissionError` if its method,
    track and budget are already there. Nothing is left behind when writing fails."""
    path = store_path(store, submission)
    if path.exists():
        raise DuplicateSubmissionError(f"the store already holds {submission.method} on the {submission.track} "
                                       f"track, {submission.budget} budget ({path.name}); a method has one "
                                       "entry per track and budget")
    write_file_atomic(path, canonical_json(submission.document))
    return path


def write_file_atomic(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` through a temporary file in the same folder and ``os.replace``."""
    path.parent.mkdir(parents=True, exist_ok=True)
    handle, temporary = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        # mkstemp creates the file private (0600); a store or site file is for everyone to read.
        os.chmod(temporary, 0o644)
        with os.fdopen(handle, "wb") as file:
            file.write(data)
            file.flush()
            os.fsync(file.fileno())
        os.replace(temporary, path)
    except BaseException:
        Path(temporary).unlink(missing_ok=True)
        raise
