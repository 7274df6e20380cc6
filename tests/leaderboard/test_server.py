"""The served board over real HTTP on loopback: uvicorn in a thread, stdlib http.client as client.

Every rejected request must leave the store directory and the database exactly as they were.
"""

from __future__ import annotations

import contextlib
import http.client
import json
import socket
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import uvicorn

from leaderboard.database import Database
from leaderboard.server import create_app
from leaderboard.store import write_submission
from leaderboard.submission import validate_submission

BODY_LIMIT = 256 * 1024


@contextlib.contextmanager
def _serving(app: Any) -> Iterator[int]:
    listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    listener.bind(("127.0.0.1", 0))
    port = listener.getsockname()[1]
    server = uvicorn.Server(uvicorn.Config(app, log_level="warning", lifespan="off"))
    thread = threading.Thread(target=server.run, kwargs={"sockets": [listener]}, daemon=True)
    thread.start()
    deadline = time.monotonic() + 10
    while not server.started:
        assert thread.is_alive() and time.monotonic() < deadline, "uvicorn did not start"
        time.sleep(0.01)
    try:
        yield port
    finally:
        server.should_exit = True
        thread.join(10)
        listener.close()


class Board:
    def __init__(self, port: int, store: Path, database: Database, token: str) -> None:
        self.port, self.store, self.database, self.token = port, store, database, token

    def request(self, method: str, path: str, body: bytes | None = None, *, token: str | None = "default",
                headers: dict[str, str] | None = None, chunked: bool = False) -> tuple[int, bytes]:
        connection = http.client.HTTPConnection("127.0.0.1", self.port, timeout=30)
        all_headers = {"Content-Type": "application/json", **(headers or {})}
        if token is not None:
            all_headers["Authorization"] = f"Bearer {self.token if token == 'default' else token}"
        try:
            if chunked:
                chunks = iter([body[i:i + 8192] for i in range(0, len(body or b""), 8192)])
                connection.request(method, path, body=chunks, headers=all_headers, encode_chunked=True)
            else:
                connection.request(method, path, body=body, headers=all_headers)
            response = connection.getresponse()
            return response.status, response.read()
        finally:
            connection.close()

    def submit(self, document: Any, **options: Any) -> tuple[int, dict[str, Any]]:
        status, body = self.request("POST", "/submissions", json.dumps(document).encode(), **options)
        return status, json.loads(body)

    def state(self) -> tuple[dict[str, bytes], list[tuple[str, str, str]]]:
        """Everything a request could change: the store's files (names and bytes) and the DB rows."""
        files = {p.name: p.read_bytes() for p in sorted(self.store.iterdir())}
        return files, self.database.submission_keys()


@pytest.fixture
def board(tmp_path: Path, make_submission, references_file: Path) -> Iterator[Board]:
    store = tmp_path / "store"
    # The store starts with entries committed through the repository: a reference point and a method.
    write_submission(store, validate_submission(make_submission("sac-source")))
    write_submission(store, validate_submission(make_submission("seeded")))
    db_url = f"sqlite:///{tmp_path / 'board.sqlite3'}"
    database = Database(db_url)
    token = database.create_token("lab-a")
    app = create_app(db_url=db_url, store=store, references=references_file, max_body_bytes=BODY_LIMIT)
    with _serving(app) as port:
        yield Board(port, store, database, token)


def test_accepted_submission_appears_on_the_page(board: Board, make_submission) -> None:
    status, page = board.request("GET", "/", token=None)
    assert status == 200 and b"sac-source (reference)" in page and b"new-method" not in page
    status, reply = board.submit(make_submission("new-method"))
    assert status == 201, reply
    assert reply == {"method": "new-method", "track": "offline-target", "budget": "lite",
                     "file": "new-method__offline-target__lite.json"}
    files, rows = board.state()
    assert rows == [("new-method", "offline-target", "lite")]
    assert validate_submission(json.loads(files["new-method__offline-target__lite.json"])).method == "new-method"
    status, page = board.request("GET", "/", token=None)
    assert status == 200, page
    assert b'data-sort="new-method"' in page, page
    assert b"27.5 [" in page
    status, table = board.request("GET", "/leaderboard.md", token=None)
    assert b"| new-method | offline-target | lite | 3 | 27.5 [" in table
    status, listing = board.request("GET", "/submissions", token=None)
    assert json.loads(listing) == [{"method": "new-method", "track": "offline-target", "budget": "lite"}]


def _nan_body(make_submission) -> bytes:
    text = json.dumps(make_submission("nan-method"))
    return text.replace('"returns": [9.0', '"returns": [NaN', 1).encode()


@pytest.mark.parametrize("case, status, message", [
    ("malformed JSON", 400, "request body: not valid JSON: Expecting"),
    ("NaN token", 400, "NaN is not valid JSON"),
    ("Infinity token", 400, "Infinity is not valid JSON"),
    ("oversized body", 413, f"request body exceeds {BODY_LIMIT} bytes"),
    ("oversized chunked body", 413, f"request body exceeds {BODY_LIMIT} bytes"),
    ("unknown task", 422, "'hopper-gravity-0.7' is not in the core suite"),
    ("missing seeds", 422, "2 training seed(s); the protocol asks for at least 3"),
    ("missing episodes", 422, "has 3 returns; the protocol evaluates exactly 4 episodes"),
    ("wrong protocol version", 422, "protocol_version '0.9'"),
    ("submitted score", 422, "'score' was unexpected"),
    ("name ../x", 422, "$.method.name: '../x' does not match"),
    ("name /etc/x", 422, "$.method.name: '/etc/x' does not match"),
    ("name a/b", 422, "$.method.name: 'a/b' does not match"),
    ("reserved name", 422, "'dap' is reserved"),
    ("missing token", 401, "missing token: send `Authorization: Bearer <token>`"),
    ("wrong token", 401, "unknown or revoked token"),
    ("duplicate of a store file", 409, "already holds seeded on the offline-target track"),
    ("reference point's name", 422, "'sac-source' is reserved"),
])
def test_rejections_change_nothing(board: Board, make_submission, case: str, status: int, message: str) -> None:
    before = board.state()
    document = make_submission("fine-method")
    options: dict[str, Any] = {}
    body: bytes | None = None
    if case == "malformed JSON":
        body = b'{"format": "offdyn-bench/submission",'
    elif case == "NaN token":
        body = _nan_body(make_submission)
    elif case == "Infinity token":
        body = json.dumps(document).replace('"returns": [9.0', '"returns": [Infinity', 1).encode()
    elif case.startswith("oversized"):
        body = b" " * (BODY_LIMIT + 1) + json.dumps(document).encode()
        options["chunked"] = case == "oversized chunked body"
    elif case == "unknown task":
        document["tasks"]["hopper-gravity-0.7"] = document["tasks"]["hopper-gravity-0.5"]
    elif case == "missing seeds":
        for entry in document["tasks"].values():
            entry["seeds"].pop()
    elif case == "missing episodes":
        document["tasks"]["ant-gravity-0.1"]["seeds"][0]["returns"].pop()
    elif case == "wrong protocol version":
        document["protocol_version"] = "0.9"
    elif case == "submitted score":
        document["score"] = 100.0
    elif case.startswith("name "):
        document["method"]["name"] = case.removeprefix("name ")
    elif case == "reserved name":
        document["method"]["name"] = "dap"
    elif case == "missing token":
        options["token"] = None
    elif case == "wrong token":
        options["token"] = board.token[:-2] + ("AA" if not board.token.endswith("AA") else "BB")
    elif case == "duplicate of a store file":
        document["method"]["name"] = "seeded"
    elif case == "reference point's name":
        document["method"]["name"] = "sac-source"
    got_status, reply = board.request("POST", "/submissions", body or json.dumps(document).encode(), **options)
    assert got_status == status, reply
    error = json.loads(reply)["error"]
    assert message in error and "\n" not in error
    assert board.state() == before
    assert not list(board.store.glob(".*"))  # no temporary file left behind


def test_duplicate_through_the_server_is_409(board: Board, make_submission) -> None:
    assert board.submit(make_submission("twice"))[0] == 201
    before = board.state()
    status, reply = board.submit(make_submission("twice", seed_means={
        "hopper-gravity-0.5": (1.0, 2.0, 3.0), "walker2d-gravity-2.0": (1.0, 2.0, 3.0),
        "ant-gravity-0.1": (1.0, 2.0, 3.0)}))
    assert status == 409 and "a method has one entry per track and budget" in reply["error"]
    assert board.state() == before
    # The same method on another track is another entry.
    assert board.submit(make_submission("twice", track="online-target"))[0] == 201


def test_revoked_token_is_refused(board: Board, make_submission) -> None:
    board.database.revoke_token("lab-a")
    before = board.state()
    status, reply = board.submit(make_submission("late"))
    assert status == 401 and reply["error"] == "unknown or revoked token"
    assert board.state() == before


def test_failed_file_write_rolls_back_the_row(board: Board, make_submission,
                                              monkeypatch: pytest.MonkeyPatch) -> None:
    import leaderboard.store

    def full_disk(path: Path, data: bytes) -> None:
        raise OSError(28, "No space left on device")

    before = board.state()
    with monkeypatch.context() as patch:
        patch.setattr(leaderboard.store, "write_file_atomic", full_disk)
        status, reply = board.request("POST", "/submissions", json.dumps(make_submission("unlucky")).encode())
    assert status == 500 and "No space left on device" in json.loads(reply)["error"]
    assert board.state() == before
    assert board.submit(make_submission("unlucky"))[0] == 201


def test_failed_commit_removes_the_file(board: Board, make_submission, monkeypatch: pytest.MonkeyPatch) -> None:
    from sqlalchemy.exc import OperationalError
    from sqlalchemy.orm import Session

    def failing_commit(self: Session) -> None:
        raise OperationalError("COMMIT", {}, Exception("database went away"))

    before = board.state()
    with monkeypatch.context() as patch:
        patch.setattr(Session, "commit", failing_commit)
        status, reply = board.request("POST", "/submissions", json.dumps(make_submission("unlucky")).encode())
    assert status == 500 and "nothing was stored" in json.loads(reply)["error"]
    assert board.state() == before


def test_concurrent_submissions_lose_nothing(board: Board, make_submission) -> None:
    documents = [make_submission(f"method-{i}") for i in range(8)]
    results: list[int] = [0] * len(documents)

    def send(index: int) -> None:
        results[index] = board.submit(documents[index])[0]

    threads = [threading.Thread(target=send, args=(i,)) for i in range(len(documents))]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(60)
    assert results == [201] * 8
    files, rows = board.state()
    expected = {f"method-{i}__offline-target__lite.json" for i in range(8)}
    assert expected <= set(files) and len(files) == 10
    assert sorted(rows) == sorted((f"method-{i}", "offline-target", "lite") for i in range(8))
    status, page = board.request("GET", "/", token=None)
    assert all(f"method-{i}".encode() in page for i in range(8))


def test_server_refuses_an_invalid_store(tmp_path: Path, small_protocol: None) -> None:
    from leaderboard.submission import SubmissionError

    store = tmp_path / "store"
    store.mkdir()
    (store / "x.json").write_text("[]")
    with pytest.raises(SubmissionError, match="x.json: expected a JSON object"):
        create_app(db_url=f"sqlite:///{tmp_path / 'db.sqlite3'}", store=store)


def test_tokens_are_stored_hashed(tmp_path: Path) -> None:
    import hashlib
    import sqlite3

    from offdyn_bench.errors import OffdynError

    database = Database(f"sqlite:///{tmp_path / 'db.sqlite3'}")
    token = database.create_token("lab-b")
    assert len(token) >= 40 and database.submitter_of(token) == "lab-b"
    rows = sqlite3.connect(tmp_path / "db.sqlite3").execute("SELECT name, token_sha256 FROM tokens").fetchall()
    assert rows == [("lab-b", hashlib.sha256(token.encode()).hexdigest())]
    with pytest.raises(OffdynError, match="a token named 'lab-b' exists"):
        database.create_token("lab-b")
    with pytest.raises(OffdynError, match="token name '../x'"):
        database.create_token("../x")
    with pytest.raises(OffdynError, match="cannot use database URL"):
        Database("nosuchdialect://x")
