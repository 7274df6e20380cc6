"""The served leaderboard (Starlette on uvicorn): the rendered board at ``/``, submissions at
``POST /submissions``.

A submission goes through, in order: the bearer token (401), the body size, enforced while the
body is read (413), strict JSON (400), :func:`leaderboard.submission.validate_submission` (422),
the names reserved for the suite's own implementations (422), a duplicate method/track/budget
(409). Only then is it written, to the database and the store together (201). A rejected request
changes nothing; its JSON body is ``{"error": "<one line: what was wrong, what was expected>"}``.
"""

from __future__ import annotations

import threading
from pathlib import Path

from sqlalchemy.exc import SQLAlchemyError
from starlette.applications import Starlette
from starlette.concurrency import run_in_threadpool
from starlette.requests import Request
from starlette.responses import HTMLResponse, JSONResponse, PlainTextResponse, Response
from starlette.routing import Route

from leaderboard.database import Database
from leaderboard.store import DuplicateSubmissionError, load_store
from leaderboard.submission import (
    MAX_SUBMISSION_BYTES,
    SCHEMA_PATH,
    Submission,
    SubmissionError,
    parse_json_strict,
    validate_submission,
)


class _BodyTooLarge(Exception):
    pass


def _error(status: int, message: str, headers: dict[str, str] | None = None) -> JSONResponse:
    return JSONResponse({"error": message}, status_code=status, headers=headers)


async def _read_body(request: Request, limit: int) -> bytes:
    """The request body, refusing as soon as it is known to exceed ``limit`` bytes: from the
    Content-Length header before reading anything, else while the chunks arrive."""
    declared = request.headers.get("content-length")
    if declared is not None and declared.isdigit() and int(declared) > limit:
        raise _BodyTooLarge(int(declared))
    chunks, size = [], 0
    async for chunk in request.stream():
        size += len(chunk)
        if size > limit:
            raise _BodyTooLarge(size)
        chunks.append(chunk)
    return b"".join(chunks)


def _reserved_names() -> frozenset[str]:
    """The suite's reference implementations and reference points: they enter the store through the
    repository, so nobody can take their names on the served board."""
    from offdyn_bench import protocol

    names = set(protocol.REFERENCE_METHODS)
    for track in protocol.TRACKS.values():
        names.update(track.methods)
    return frozenset(names)


class _Board:
    """The rendered page, rebuilt after each accepted submission (rendering takes about a second)."""

    def __init__(self, store: Path, references: Path | None) -> None:
        self.store = store
        self.references = references
        self._lock = threading.Lock()
        self._generation = 0
        self._rendered: tuple[int, str, str] | None = None

    def changed(self) -> None:
        with self._lock:
            self._generation += 1

    def pages(self) -> tuple[str, str]:
        """(index.html, leaderboard.md) of the store as it is now."""
        from leaderboard.render import render_html, render_markdown
        from leaderboard.scores import score_board

        with self._lock:
            if self._rendered is not None and self._rendered[0] == self._generation:
                return self._rendered[1], self._rendered[2]
            generation = self._generation
            board = score_board(load_store(self.store), references=self.references)
            self._rendered = (generation, render_html(board), render_markdown(board))
            return self._rendered[1], self._rendered[2]


def create_app(*, db_url: str, store: Path, references: Path | None = None,
               max_body_bytes: int = MAX_SUBMISSION_BYTES) -> Starlette:
    """The leaderboard app. Validates every file of ``store`` first: a server never starts on a
    store it could not render."""
    if max_body_bytes < 1:
        raise SubmissionError(f"max body bytes {max_body_bytes}; expected a positive number of bytes")
    store.mkdir(parents=True, exist_ok=True)
    load_store(store)
    database = Database(db_url)
    board = _Board(store, references)
    reserved = _reserved_names()

    async def index(request: Request) -> Response:
        page, _ = await run_in_threadpool(board.pages)
        return HTMLResponse(page)

    async def markdown(request: Request) -> Response:
        _, table = await run_in_threadpool(board.pages)
        return PlainTextResponse(table, media_type="text/markdown; charset=utf-8")

    async def schema(request: Request) -> Response:
        return Response(SCHEMA_PATH.read_bytes(), media_type="application/schema+json")

    async def list_submissions(request: Request) -> Response:
        keys = await run_in_threadpool(database.submission_keys)
        return JSONResponse([{"method": m, "track": t, "budget": b} for m, t, b in keys])

    def accept(submission: Submission, submitter: str) -> Path:
        if submission.method in reserved:
            raise SubmissionError(f"method name {submission.method!r} is reserved for the suite's own "
                                  "implementation; choose another name")
        path = database.add_submission(submission, store, submitter)
        board.changed()
        return path

    async def submit(request: Request) -> Response:
        authorization = request.headers.get("authorization", "")
        scheme, _, token = authorization.partition(" ")
        if scheme.lower() != "bearer" or not token.strip():
            return _error(401, "missing token: send `Authorization: Bearer <token>` (tokens come from "
                               "`offdyn-bench leaderboard token create`)", {"WWW-Authenticate": "Bearer"})
        submitter = await run_in_threadpool(database.submitter_of, token.strip())
        if submitter is None:
            return _error(401, "unknown or revoked token", {"WWW-Authenticate": 'Bearer error="invalid_token"'})
        try:
            body = await _read_body(request, max_body_bytes)
        except _BodyTooLarge:
            return _error(413, f"request body exceeds {max_body_bytes} bytes; a submission holds raw returns "
                               "and optional learning curves only")
        try:
            document = parse_json_strict(body, source="request body", max_bytes=max_body_bytes)
        except SubmissionError as error:
            return _error(400, str(error))
        try:
            submission = await run_in_threadpool(validate_submission, document, source="submission")
            path = await run_in_threadpool(accept, submission, submitter)
        except DuplicateSubmissionError as error:
            return _error(409, str(error))
        except SubmissionError as error:
            return _error(422, str(error))
        except (OSError, SQLAlchemyError) as error:
            # add_submission has undone its half: neither the row nor the file exists.
            return _error(500, f"could not record the submission ({type(error).__name__}: {error}); nothing "
                               "was stored, try again later")
        return JSONResponse({"method": submission.method, "track": submission.track, "budget": submission.budget,
                             "file": path.name}, status_code=201)

    return Starlette(routes=[
        Route("/", index, methods=["GET"]),
        Route("/leaderboard.md", markdown, methods=["GET"]),
        Route("/schema/submission-v1.json", schema, methods=["GET"]),
        Route("/submissions", list_submissions, methods=["GET"]),
        Route("/submissions", submit, methods=["POST"]),
    ])
