"""Remotes that misbehave at the socket level: garbage instead of HTTP, bytes that trickle in
too slowly, transfers that never end. Each gives a one-line DownloadError and installs nothing."""

from __future__ import annotations

import socket
import time

import pytest

from offdyn_bench.datasets import DownloadError, download_dataset
from offdyn_bench.datasets.manifest import Manifest, archive_name, entry_name
from offdyn_bench.datasets.transfer import TransferError, TransferLimits

EMPTY = Manifest({})
DATASET_ID = "offdyn/hopper-gravity-0p5/random-v0"
# Tiny limits, so the slow cases fail in about a second.
TINY = TransferLimits(deadline_s=1.5, min_rate_bytes_per_s=200, rate_window_s=0.6, read_timeout_s=5)


def trickle(conn: socket.socket, data: bytes, every_s: float, limit_s: float = 20) -> None:
    """Send ``data`` one byte at a time, ``every_s`` apart (stops when the client hangs up)."""
    ends = time.monotonic() + limit_s
    for byte in data:
        if time.monotonic() > ends:
            return
        conn.sendall(bytes([byte]))
        time.sleep(every_s)


def headers(length: int) -> bytes:
    return f"HTTP/1.1 200 OK\r\nContent-Length: {length}\r\n\r\n".encode()


@pytest.mark.parametrize("reply", [b"garbage\r\n\r\n", b"HTTP/1.1 abc OK\r\n\r\n", b"\x00\xff" * 40 + b"\r\n"])
def test_garbage_status_line_is_a_download_error(reply: bytes, raw_server, nothing_installed) -> None:
    url = raw_server(lambda conn, request: conn.sendall(reply))
    with pytest.raises(DownloadError, match="not valid HTTP .*is the remote URL right"):
        download_dataset(DATASET_ID, remote=url, manifest=EMPTY)
    nothing_installed(DATASET_ID)


def test_garbage_while_reading_the_archive_is_a_download_error(published, raw_server, nothing_installed) -> None:
    recipe, _, remote = published
    entry = (remote / entry_name(recipe.dataset_id)).read_bytes()

    def serve(conn: socket.socket, request: bytes) -> None:
        if entry_name(recipe.dataset_id).encode() in request:
            conn.sendall(headers(len(entry)) + entry)
        else:  # chunked, with a chunk size that is not hex
            conn.sendall(b"HTTP/1.1 200 OK\r\nTransfer-Encoding: chunked\r\n\r\nzz\r\nabc\r\n")

    with pytest.raises(DownloadError, match="interrupted .*IncompleteRead"):
        download_dataset(recipe.dataset_id, remote=raw_server(serve), manifest=EMPTY, limits=TINY)
    nothing_installed(recipe.dataset_id)


@pytest.mark.timeout(30)
def test_a_trickling_archive_falls_below_the_minimum_rate(published, raw_server, nothing_installed) -> None:
    recipe, result, remote = published
    entry = (remote / entry_name(recipe.dataset_id)).read_bytes()
    archive = (remote / archive_name(recipe.dataset_id)).read_bytes()

    def serve(conn: socket.socket, request: bytes) -> None:
        if entry_name(recipe.dataset_id).encode() in request:
            conn.sendall(headers(len(entry)) + entry)
        else:  # one byte every 50 ms: each read returns, so no per-read timeout ever fires
            conn.sendall(headers(len(archive)))
            trickle(conn, archive, every_s=0.05)

    limits = TransferLimits(deadline_s=600, min_rate_bytes_per_s=200, rate_window_s=0.6, read_timeout_s=5)
    with pytest.raises(DownloadError, match="bytes/s over the last .* below the minimum of 200 bytes/s "
                                            r"\(set OFFDYN_DOWNLOAD_MIN_RATE"):
        download_dataset(recipe.dataset_id, remote=raw_server(serve), manifest=EMPTY, limits=limits)
    nothing_installed(recipe.dataset_id)


@pytest.mark.timeout(30)
def test_a_status_line_sent_byte_by_byte_is_stopped(raw_server, nothing_installed) -> None:
    # The reader is blocked inside http.client's readline: only the watchdog can stop it.
    url = raw_server(lambda conn, request: trickle(conn, b"HTTP/1.1 200 OK\r\n" * 100, every_s=0.2))
    with pytest.raises(DownloadError, match="below the minimum"):
        download_dataset(DATASET_ID, remote=url, manifest=EMPTY, limits=TINY)
    nothing_installed(DATASET_ID)


@pytest.mark.timeout(30)
def test_a_steady_but_endless_transfer_hits_the_deadline(raw_server, nothing_installed) -> None:
    # 1000 bytes/s, well above the minimum rate, for longer than the deadline.
    url = raw_server(lambda conn, request: (conn.sendall(headers(10**6)), trickle(conn, b"{" * 10**6, every_s=0.001)))
    limits = TransferLimits(deadline_s=1.0, min_rate_bytes_per_s=10, rate_window_s=0.5, read_timeout_s=5)
    with pytest.raises(DownloadError, match=r"past the 1 s deadline \(set OFFDYN_DOWNLOAD_DEADLINE"):
        download_dataset(DATASET_ID, remote=url, manifest=EMPTY, limits=limits)
    nothing_installed(DATASET_ID)


def test_a_fast_transfer_under_tiny_limits_succeeds(published, loopback_remote, nothing_installed) -> None:
    # The limits stop slow transfers only: the same tiny limits let a fast one through.
    recipe, result, remote = published
    for name in (archive_name(recipe.dataset_id), entry_name(recipe.dataset_id)):
        (loopback_remote.folder / name).parent.mkdir(parents=True, exist_ok=True)
        (loopback_remote.folder / name).write_bytes((remote / name).read_bytes())
    path = download_dataset(recipe.dataset_id, remote=loopback_remote.url, manifest=EMPTY, limits=TINY)
    assert (path / "data" / "metadata.json").is_file()


def test_limits_from_the_environment() -> None:
    limits = TransferLimits.from_environment({"OFFDYN_DOWNLOAD_DEADLINE": "120", "OFFDYN_DOWNLOAD_MIN_RATE": "0",
                                              "OFFDYN_DOWNLOAD_RATE_WINDOW": "10"})
    assert limits == TransferLimits(deadline_s=120, min_rate_bytes_per_s=0, rate_window_s=10)
    assert TransferLimits.from_environment({}) == TransferLimits()
    assert TransferLimits().deadline_s == 3600 and TransferLimits().min_rate_bytes_per_s == 1024


@pytest.mark.parametrize("variable, value, expected", [
    ("OFFDYN_DOWNLOAD_DEADLINE", "soon", "OFFDYN_DOWNLOAD_DEADLINE='soon': not a number of seconds"),
    ("OFFDYN_DOWNLOAD_DEADLINE", "-1", "deadline_s=-1.0; expected a finite number of seconds > 0"),
    ("OFFDYN_DOWNLOAD_MIN_RATE", "fast", "not a number of bytes per second"),
    ("OFFDYN_DOWNLOAD_MIN_RATE", "nan", "expected a finite number >= 0"),
    ("OFFDYN_DOWNLOAD_RATE_WINDOW", "0", "rate_window_s=0.0; expected a finite number of seconds > 0"),
])
def test_bad_limits_in_the_environment_are_named(variable: str, value: str, expected: str, monkeypatch) -> None:
    with pytest.raises(TransferError, match=expected):
        TransferLimits.from_environment({variable: value})
    monkeypatch.setenv(variable, value)
    with pytest.raises(TransferError, match=variable):  # a download reads them before any request
        download_dataset(DATASET_ID, remote="http://127.0.0.1:9/", manifest=EMPTY)
