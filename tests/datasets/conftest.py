"""Dataset fixtures; the isolated Minari root and remote of every test come from tests/conftest.py."""

from __future__ import annotations

import contextlib
import dataclasses
import http.server
import pathlib
import socket
import threading
from collections.abc import Callable, Iterator

import pytest

# Minari's HDF5 storage (the datasets' format) needs h5py, which plain `minari` does not pull in:
# the project must depend on minari[hdf5]. Without it, say so instead of failing every test.
pytest.importorskip("h5py", reason="h5py missing: the project needs minari[hdf5]==0.5.4 (pyproject.toml)")

import offdyn_bench  # noqa: E402,F401 - registers the task ids
from offdyn_bench.datasets.build import BuildResult, build_dataset  # noqa: E402
from offdyn_bench.datasets.recipes import Recipe, default_recipe  # noqa: E402


def tiny_recipe(task: str = "hopper-gravity-0.5", quality: str = "random", transitions: int = 150,
                **changes: object) -> Recipe:
    """The default recipe of ``task``, cut down to a few episodes and two reference episodes."""
    recipe = default_recipe(task, quality, num_transitions=transitions)
    return dataclasses.replace(recipe, reference_episodes=2, **changes)  # type: ignore[arg-type]


@pytest.fixture(name="tiny_recipe")
def tiny_recipe_fixture() -> Callable[..., Recipe]:
    return tiny_recipe


@pytest.fixture(scope="session")
def published(tmp_path_factory: pytest.TempPathFactory) -> tuple[Recipe, BuildResult, pathlib.Path]:
    """A tiny dataset built once into a remote folder (its archive, entry and datasets.json)."""
    remote = tmp_path_factory.mktemp("remote")
    recipe = tiny_recipe()
    result = build_dataset(recipe, root=tmp_path_factory.mktemp("build-root"), out_dir=remote, install=False)
    return recipe, result, remote


@dataclasses.dataclass
class LoopbackRemote:
    """A loopback HTTP server over a folder, with faults a test can switch on."""

    folder: pathlib.Path
    url: str
    # path -> how many bytes to send before dropping the connection (Content-Length stays full)
    cut_after: dict[str, int] = dataclasses.field(default_factory=dict)
    requests: list[str] = dataclasses.field(default_factory=list)


@pytest.fixture
def loopback_remote(tmp_path: pathlib.Path) -> Iterator[LoopbackRemote]:
    folder = tmp_path / "served"
    folder.mkdir()
    state = LoopbackRemote(folder=folder, url="")

    class Handler(http.server.BaseHTTPRequestHandler):
        def do_GET(self) -> None:  # noqa: N802 - http.server's name
            rel = self.path.lstrip("/")
            state.requests.append(rel)
            path = folder / rel
            if ".." in rel.split("/") or not path.is_file():
                self.send_error(404)
                return
            body = path.read_bytes()
            self.send_response(200)
            self.send_header("Content-Length", str(len(body)))
            self.end_headers()
            if rel in state.cut_after:
                self.wfile.write(body[: state.cut_after.pop(rel)])
                self.wfile.flush()
                self.close_connection = True
                return
            self.wfile.write(body)

        def log_message(self, *args: object) -> None:
            pass

    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Handler)
    state.url = f"http://127.0.0.1:{server.server_address[1]}"
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        yield state
    finally:
        server.shutdown()
        server.server_close()
        thread.join(timeout=5)


@pytest.fixture
def raw_server() -> Iterator[Callable[[Callable[[socket.socket, bytes], None]], str]]:
    """Start a loopback TCP server whose every connection is handled by a given function of the
    socket and the request's bytes (to send garbage, or trickle bytes); returns its http://
    URL. Connections are closed on exit."""
    listeners: list[socket.socket] = []
    stop = threading.Event()
    threads: list[threading.Thread] = []

    def start(handle: Callable[[socket.socket, bytes], None]) -> str:
        listener = socket.create_server(("127.0.0.1", 0))
        listener.settimeout(0.1)
        listeners.append(listener)

        def serve() -> None:
            while not stop.is_set():
                try:
                    conn, _ = listener.accept()
                except (TimeoutError, OSError):
                    continue
                with conn:
                    conn.settimeout(5)
                    with contextlib.suppress(OSError):
                        handle(conn, conn.recv(65536))

        thread = threading.Thread(target=serve, daemon=True)
        thread.start()
        threads.append(thread)
        return f"http://127.0.0.1:{listener.getsockname()[1]}"

    try:
        yield start
    finally:
        stop.set()
        for thread in threads:
            thread.join(timeout=10)
        for listener in listeners:
            listener.close()


@pytest.fixture
def nothing_installed(isolated_paths: pathlib.Path) -> Callable[[str], None]:
    """Asserts that ``dataset_id`` is not installed and no staging is left under the test's root."""
    from offdyn_bench.datasets.install import STAGING_DIR, is_installed

    def check(dataset_id: str) -> None:
        assert not is_installed(dataset_id, isolated_paths)
        assert not (isolated_paths / dataset_id).exists()
        assert not (isolated_paths / STAGING_DIR).exists() or not any((isolated_paths / STAGING_DIR).iterdir())

    return check
