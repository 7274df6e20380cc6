"""Reading one file from a remote under limits that a slow or hostile server cannot evade.

A socket timeout bounds each read, not a transfer: a server that sends one byte every few
seconds never trips it. A transfer here also has an overall deadline and a minimum rate,
measured over a sliding window. A watchdog thread checks both while the reader may be blocked
(in a read, or still waiting for the status line) and shuts the connection's socket down when
one is broken, which wakes the reader; the error then names the limit and how to change it.

Limits come from :class:`TransferLimits`, by default from the environment:

- ``OFFDYN_DOWNLOAD_DEADLINE`` (seconds, default 3600): the longest one file may take, from
  connecting to its last byte;
- ``OFFDYN_DOWNLOAD_MIN_RATE`` (bytes/s, default 1024): the slowest average rate accepted over
  any ``OFFDYN_DOWNLOAD_RATE_WINDOW`` seconds (default 30) once that long has passed;
- a single read (and connecting) times out after ``read_timeout_s`` (60 s).
"""

from __future__ import annotations

import collections
import contextlib
import dataclasses
import http.client
import math
import os
import socket
import threading
import time
import urllib.error
import urllib.request
from collections.abc import Callable, Iterator, Mapping
from typing import Any

from offdyn_bench.errors import OffdynError

DEADLINE_ENV = "OFFDYN_DOWNLOAD_DEADLINE"
MIN_RATE_ENV = "OFFDYN_DOWNLOAD_MIN_RATE"
RATE_WINDOW_ENV = "OFFDYN_DOWNLOAD_RATE_WINDOW"
_CHUNK = 1 << 16


class TransferError(OffdynError):
    """A remote file that could not be read completely within the limits."""


class RemoteNotFoundError(TransferError):
    """The remote has no such file (HTTP 404, or a missing file under a file:// remote)."""


@dataclasses.dataclass(frozen=True)
class TransferLimits:
    """How long one remote file may take and how slowly it may arrive."""

    deadline_s: float = 3600.0
    min_rate_bytes_per_s: float = 1024.0
    rate_window_s: float = 30.0
    read_timeout_s: float = 60.0

    def __post_init__(self) -> None:
        for name in ("deadline_s", "rate_window_s", "read_timeout_s"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise TransferError(f"transfer limit {name}={value!r}; expected a finite number of seconds > 0")
        rate = self.min_rate_bytes_per_s
        if not (isinstance(rate, (int, float)) and math.isfinite(rate) and rate >= 0):
            raise TransferError(f"transfer limit min_rate_bytes_per_s={rate!r}; expected a finite number >= 0 "
                                "(0 turns the rate check off)")

    @classmethod
    def from_environment(cls, environ: Mapping[str, str] | None = None) -> TransferLimits:
        """The defaults, overridden by ``OFFDYN_DOWNLOAD_DEADLINE``, ``OFFDYN_DOWNLOAD_MIN_RATE``
        and ``OFFDYN_DOWNLOAD_RATE_WINDOW`` where set."""
        environ = os.environ if environ is None else environ
        values: dict[str, float] = {}
        for variable, field in ((DEADLINE_ENV, "deadline_s"), (MIN_RATE_ENV, "min_rate_bytes_per_s"),
                                (RATE_WINDOW_ENV, "rate_window_s")):
            text = environ.get(variable)
            if text is None or text.strip() == "":
                continue
            try:
                values[field] = float(text)
                cls(**{field: values[field]})
            except (ValueError, TransferError) as error:
                expected = "bytes per second" if field == "min_rate_bytes_per_s" else "seconds"
                detail = str(error) if isinstance(error, TransferError) else f"not a number of {expected}"
                raise TransferError(f"{variable}={text!r}: {detail}") from None
        return cls(**values)


class _Watchdog:
    """Counts a transfer's bytes, and shuts its sockets down once a limit is broken."""

    def __init__(self, url: str, limits: TransferLimits) -> None:
        self.url = url
        self.limits = limits
        self.started = time.monotonic()
        self.received = 0
        self.broken: str | None = None  # which limit, once one is
        self._sockets: list[socket.socket] = []
        self._samples: collections.deque[tuple[float, int]] = collections.deque([(self.started, 0)])
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._watch, name="offdyn-transfer-watchdog", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        self._thread.join()

    def add_socket(self, sock: socket.socket) -> None:
        with self._lock:
            self._sockets.append(sock)
            broken = self.broken
        if broken is not None:
            self._shut(sock)

    def count(self, nbytes: int) -> None:
        self.received += nbytes
        self.check()

    def check(self) -> None:
        """Raise if a limit is broken (also called by the reader between reads)."""
        broken = self.broken or self._limit_broken(time.monotonic())
        if broken is not None:
            self._break(broken)
            raise TransferError(f"{self.url}: {broken}; nothing was installed")

    def _limit_broken(self, now: float) -> str | None:
        limits = self.limits
        elapsed = now - self.started
        if elapsed > limits.deadline_s:
            return (f"not complete after {elapsed:.1f} s ({self.received} bytes received), past the "
                    f"{limits.deadline_s:g} s deadline (set {DEADLINE_ENV} to allow longer)")
        with self._lock:  # the watchdog and the reader both sample
            received = self.received
            if limits.min_rate_bytes_per_s > 0 and elapsed >= limits.rate_window_s:
                while len(self._samples) > 1 and self._samples[1][0] <= now - limits.rate_window_s:
                    self._samples.popleft()
                since, then_received = self._samples[0]
                rate = (received - then_received) / max(now - since, 1e-9)
                if rate < limits.min_rate_bytes_per_s:
                    return (f"{rate:.1f} bytes/s over the last {now - since:.1f} s, below the minimum of "
                            f"{limits.min_rate_bytes_per_s:g} bytes/s (set {MIN_RATE_ENV} to accept slower "
                            "transfers)")
            self._samples.append((now, received))
        return None

    def _break(self, reason: str) -> None:
        with self._lock:
            if self.broken is None:
                self.broken = reason
            sockets = list(self._sockets)
        for sock in sockets:
            self._shut(sock)

    @staticmethod
    def _shut(sock: socket.socket) -> None:
        # socket.socket's own shutdown, also for an SSL socket: it wakes a blocked recv in the
        # reader's thread without touching the TLS state that thread is using.
        with contextlib.suppress(OSError):
            socket.socket.shutdown(sock, socket.SHUT_RDWR)

    def _watch(self) -> None:
        tick = min(0.25, self.limits.rate_window_s / 4, self.limits.deadline_s / 4)
        while not self._stop.wait(tick):
            reason = self._limit_broken(time.monotonic())
            if reason is not None:
                self._break(reason)
                return


def _watched_connection(base: type[http.client.HTTPConnection],
                        watchdog: _Watchdog) -> Callable[..., http.client.HTTPConnection]:
    class Watched(base):  # type: ignore[valid-type, misc]
        def connect(self) -> None:
            super().connect()
            watchdog.add_socket(self.sock)

    return Watched


class _HTTPHandler(urllib.request.HTTPHandler):
    def __init__(self, watchdog: _Watchdog) -> None:
        super().__init__()
        self._connection = _watched_connection(http.client.HTTPConnection, watchdog)

    def http_open(self, req: urllib.request.Request) -> Any:
        return self.do_open(self._connection, req)


class _HTTPSHandler(urllib.request.HTTPSHandler):
    def __init__(self, watchdog: _Watchdog) -> None:
        super().__init__()
        self._connection = _watched_connection(http.client.HTTPSConnection, watchdog)

    def https_open(self, req: urllib.request.Request) -> Any:
        return self.do_open(self._connection, req, context=self._context)


class RemoteFile:
    """An open remote file: :meth:`chunks` yields its bytes as they arrive."""

    def __init__(self, url: str, response: Any, watchdog: _Watchdog) -> None:
        self.url = url
        self._response = response
        self._watchdog = watchdog

    @property
    def received(self) -> int:
        return self._watchdog.received

    def chunks(self) -> Iterator[bytes]:
        # read1 returns what one socket read brings; read(n) would wait for all n bytes, which
        # at one byte every few seconds is never, and never trips the per-read timeout either.
        read = getattr(self._response, "read1", self._response.read)
        while True:
            try:
                block = read(_CHUNK)
            except (OSError, http.client.HTTPException, ValueError) as error:
                self._watchdog.check()  # a limit that shut the socket down explains the error
                raise TransferError(f"download of {self.url} interrupted after {self.received} bytes "
                                    f"({type(error).__name__}: {error}); nothing was installed, run the command "
                                    "again") from error
            if not block:
                self._watchdog.check()
                return
            self._watchdog.count(len(block))
            yield block


@contextlib.contextmanager
def open_remote(url: str, limits: TransferLimits | None = None) -> Iterator[RemoteFile]:
    """Open ``url`` (http, https or file) under ``limits``; every failure to reach it or read it
    is a :class:`TransferError` (:class:`RemoteNotFoundError` for a 404 or a missing file)."""
    limits = limits if limits is not None else TransferLimits.from_environment()
    watchdog = _Watchdog(url, limits)
    opener = urllib.request.build_opener(_HTTPHandler(watchdog), _HTTPSHandler(watchdog))
    watchdog.start()
    try:
        try:
            response = opener.open(url, timeout=limits.read_timeout_s)
        except urllib.error.HTTPError as error:
            error.close()
            if error.code == 404:
                raise RemoteNotFoundError(f"{url} not found on the remote (HTTP 404): is the dataset id right, and "
                                          "has the remote been published with this dataset?") from error
            raise TransferError(f"{url}: HTTP {error.code} {error.reason}") from error
        except (urllib.error.URLError, OSError, http.client.HTTPException, ValueError) as error:
            watchdog.check()
            reason = getattr(error, "reason", error)
            if isinstance(reason, FileNotFoundError):  # file:// remotes
                raise RemoteNotFoundError(f"{url} not found on the remote: is the dataset id right, and has the "
                                          "remote been published with this dataset?") from error
            if isinstance(error, http.client.HTTPException):
                raise TransferError(f"{url}: the server's reply is not valid HTTP ({type(error).__name__}: "
                                    f"{str(error)[:120]!r}); is the remote URL right?") from error
            raise TransferError(f"cannot reach {url}: {reason}") from error
        with response:
            yield RemoteFile(url, response, watchdog)
    finally:
        watchdog.stop()


__all__ = ["TransferLimits", "TransferError", "RemoteNotFoundError", "RemoteFile", "open_remote",
           "DEADLINE_ENV", "MIN_RATE_ENV", "RATE_WINDOW_ENV"]
