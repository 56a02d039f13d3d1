"""The read-only HTTP dashboard: one page, JSON under ``/api/``, Prometheus text at ``/metrics``.

Standard library only (``http.server.ThreadingHTTPServer``), bound to a local
port. Every handler is a GET (or HEAD) that reads; nothing changes state. The data comes
from ``DashboardSources``, a bundle of callables, so the same server shows an
in-process service (``activecollect run``) or just a data directory.

Endpoints: ``/`` (the page), ``/api/stats``, ``/api/queue``, ``/api/workers``,
``/api/models``, ``/api/curve``, ``/frames.png`` (predicted vs real frames of the
champion), ``/metrics``.
"""

from __future__ import annotations

import functools
import io
import json
import logging
import socket
import sys
import threading
import time
from contextlib import contextmanager
from dataclasses import dataclass, field
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import Any, Callable, Iterator
from urllib.parse import urlsplit

from orchestrator.dashboard_page import render_page
from orchestrator.dashboard_reader import DeadlineReader
from orchestrator.metrics import ServiceMetrics
from orchestrator.storagehealth import StorageHealth
from storage.database import DB_NAME, busy_timeout, disk_json
from storage.catalog import Catalog
from storage.jsonsafe import finite_json
from storage.errors import CatalogError, StorageError, StorageUnavailableError
from storage.models import ModelRegistry
from storage.queue import RequestQueue

log = logging.getLogger(__name__)

PROMETHEUS_CONTENT_TYPE = "text/plain; version=0.0.4; charset=utf-8"
_TEXT = "text/plain; charset=utf-8"
SERVER_NAME = "activecollect-dashboard"
"""The ``Server`` header: no version of this package or of Python for a scanner to match."""


#: What a 503 for a data directory that cannot be read now (busy, locked, a full disk) asks a client to wait.
RETRY_AFTER_S = 5

#: How long a request waits for a locked database before its 503: well inside a scraper's timeout (Prometheus's
#: default is 10 s), where the stores' own 30 s made every scrape of a locked directory time out instead, and
#: held a connection slot for all that time.
READ_BUSY_TIMEOUT_S = 2.0

#: The longest request timeout (a day): sockets refuse timeouts past ~9e9 s, and every connection's
#: handler would die on one; the shortest, a tenth of a second (at 1e-300 every client was dropped).
MAX_REQUEST_TIMEOUT_S, MIN_REQUEST_TIMEOUT_S = 86400.0, 0.1


@dataclass
class DashboardConfig:
    """Where and how the dashboard serves."""

    host: str = "127.0.0.1"
    """Address to bind; keep it local, the dashboard has no authentication."""
    port: int = 8765
    """TCP port (0 picks a free one; see ``Dashboard.url``)."""
    refresh_s: float = 2.0
    """How often the page re-reads the numbers."""
    queue_rows: int = 50
    """How many of the latest requests the queue table shows."""
    request_timeout_s: float = 10.0
    """How long a client may take to send its whole request (line and headers), however it trickles in."""
    max_connections: int = 32
    """Connections served at once; one more is answered 503 (``Retry-After``) and closed, given no thread."""

    def __post_init__(self) -> None:
        if not 0 <= self.port <= 65535:
            raise ValueError(f"port must be in [0, 65535], found {self.port}")
        if not MIN_REQUEST_TIMEOUT_S <= self.request_timeout_s <= MAX_REQUEST_TIMEOUT_S:
            raise ValueError(f"request_timeout_s must be in [{MIN_REQUEST_TIMEOUT_S:g}, {MAX_REQUEST_TIMEOUT_S:g}], "
                             f"found {self.request_timeout_s}")
        if self.max_connections < 1:
            raise ValueError(f"max_connections must be >= 1, found {self.max_connections}")
        if self.refresh_s <= 0 or self.queue_rows < 1:
            raise ValueError(f"refresh_s > 0 and queue_rows >= 1 expected, found {self.refresh_s}, {self.queue_rows}")


@dataclass
class DashboardSources:
    """What the dashboard shows; each callable returns JSON-able data and must be thread-safe."""

    stats: Callable[[], dict]
    queue: Callable[[int], dict]
    workers: Callable[[], list[dict]]
    models: Callable[[], dict]
    curve: Callable[[], list[dict]]
    metrics_text: Callable[[], str] = lambda: ""
    frames_png: Callable[[], bytes] = lambda: b""


class _Server(ThreadingHTTPServer):
    """A thread per connection, at most ``max_connections`` of them; one more is refused from the accepting thread."""

    daemon_threads = True
    request_queue_size = socket.SOMAXCONN  # the default 5 made a burst of scrapes wait on SYN retries

    def __init__(self, address: tuple[str, int], handler: type[BaseHTTPRequestHandler], max_connections: int) -> None:
        self._slots = threading.BoundedSemaphore(max_connections)
        super().__init__(address, handler)

    def process_request(self, request: socket.socket, client_address: Any) -> None:
        if not self._slots.acquire(blocking=False):
            log.debug("dashboard: %s refused, already serving the most connections at once", client_address)
            _refuse(request)
            self.shutdown_request(request)
            return
        try:
            super().process_request(request, client_address)
        except BaseException:  # no thread started, so none will give the slot back
            self._slots.release()
            raise

    def handle_error(self, request: Any, client_address: Any) -> None:
        """A client that went away (reset, broken pipe) is no error of ours; anything else is logged with
        its traceback (the base class prints every one to stderr)."""
        exc = sys.exc_info()[1]
        if isinstance(exc, (ConnectionError, TimeoutError)):
            log.debug("dashboard: %s went away: %s", client_address, exc)
        else:
            log.error("dashboard: the request from %s failed", client_address, exc_info=True)

    def process_request_thread(self, request: socket.socket, client_address: Any) -> None:
        try:  # the base class catches the handler's exceptions and closes the socket; the slot goes back after
            super().process_request_thread(request, client_address)
        finally:
            self._slots.release()


_BUSY_BODY = b"the dashboard is serving too many connections; retry in a second\n"
_BUSY = (b"HTTP/1.0 503 Service Unavailable\r\n"
         b"Server: " + SERVER_NAME.encode() + b"\r\n"
         b"X-Content-Type-Options: nosniff\r\n"
         b"Retry-After: 1\r\n"
         b"Content-Type: text/plain; charset=utf-8\r\n"
         b"Content-Length: " + str(len(_BUSY_BODY)).encode() + b"\r\n"
         b"Connection: close\r\n"
         b"\r\n" + _BUSY_BODY)


def _refuse(sock: socket.socket) -> None:
    """Answer 503 without ever blocking the accepting thread: a client that cannot take it now goes without."""
    sock.setblocking(False)
    try:
        sock.send(_BUSY)
    except OSError as exc:  # its buffer is full or it is gone; it is closed either way
        log.debug("dashboard: the 503 was not sent: %s", exc)
    try:  # what the client already sent: closing over unread bytes resets the connection, and may lose the 503
        sock.recv(65536)
    except OSError:  # nothing has arrived yet (BlockingIOError), or the client is gone: nothing to read
        pass


class Dashboard:
    """A ThreadingHTTPServer in a daemon thread; ``start`` / ``stop``."""

    def __init__(self, cfg: DashboardConfig, sources: DashboardSources) -> None:
        self.cfg = cfg
        self.sources = sources
        self._server: ThreadingHTTPServer | None = None
        self._thread: threading.Thread | None = None
        # a page refreshing every few seconds meets a broken data directory on every read: said once a minute
        self._health = StorageHealth(log)

    @property
    def url(self) -> str:
        if self._server is None:
            raise RuntimeError("the dashboard is not started")
        host, port = self._server.server_address[:2]
        return f"http://{host}:{port}/"

    def start(self) -> None:
        handler = type("Handler", (_Handler,), {"dashboard": self, "timeout": self.cfg.request_timeout_s})
        self._server = _Server((self.cfg.host, self.cfg.port), handler, self.cfg.max_connections)
        self._thread = threading.Thread(target=self._server.serve_forever, name="dashboard", daemon=True)
        self._thread.start()
        log.info("dashboard on %s", self.url)

    def stop(self) -> None:
        if self._server is not None:
            self._server.shutdown()
            self._server.server_close()
        if self._thread is not None:
            self._thread.join()
        self._server = self._thread = None

    def answer(self, path: str) -> tuple[int, str, bytes, dict[str, str]]:
        """(status, content type, body, extra headers) for a GET of ``path``: ``route``'s, or its failure in one
        line. A data directory that cannot be read is a 503 (``Retry-After``) when that passes (busy, locked,
        full), else a 500, warned of at most once a minute per path; anything else is a bug of ours, logged
        with its traceback."""
        try:
            with busy_timeout(READ_BUSY_TIMEOUT_S):
                status, ctype, body = self.route(path)
        except StorageError as exc:
            self._health.read_failed(f"{path} for the dashboard", exc)
            if isinstance(exc, StorageUnavailableError):
                return 503, _TEXT, f"{exc}\n".encode(), {"Retry-After": str(RETRY_AFTER_S)}
            return 500, _TEXT, f"{exc}\n".encode(), {}
        except Exception as exc:  # one broken source must not take the page down; it is logged
            log.exception("dashboard %s failed", path)
            return 500, _TEXT, f"{type(exc).__name__}: {exc}\n".encode(), {}
        if status == 200:  # only the known paths: a scan of made-up ones must not grow what is remembered
            self._health.read_worked(f"{path} for the dashboard")
        return status, ctype, body, {}

    def route(self, path: str) -> tuple[int, str, bytes]:
        """(status, content type, body) for a GET of ``path``."""
        src = self.sources
        if path in ("/", "/index.html"):
            return 200, "text/html; charset=utf-8", render_page(self.cfg.refresh_s)
        if path == "/metrics":
            return 200, PROMETHEUS_CONTENT_TYPE, src.metrics_text().encode()
        if path == "/frames.png":
            return 200, "image/png", src.frames_png() or _placeholder_png()
        api: dict[str, Callable[[], Any]] = {
            "/api/stats": src.stats,
            "/api/queue": lambda: src.queue(self.cfg.queue_rows),
            "/api/workers": lambda: {"workers": src.workers()},
            "/api/models": src.models,
            "/api/curve": lambda: {"points": src.curve()},
        }
        if path in api:
            return 200, "application/json", json.dumps(finite_json(api[path]()), default=str).encode()
        return 404, _TEXT, f"no such page: {path}\n".encode()


class _Handler(BaseHTTPRequestHandler):
    """GET and HEAD; every other method is 405. One request per connection (HTTP/1.0, the base class's default)."""

    dashboard: Dashboard
    server_version = SERVER_NAME
    # what an error found before the request's version is read is answered as: the base class's HTTP/0.9 sent a
    # bare body, without a status line or headers (a request line with a bad or unknown version)
    default_request_version = "HTTP/1.0"

    def setup(self) -> None:
        super().setup()
        self.rfile.close()  # the base class's reader; an open one would keep the socket from closing
        self._reader = DeadlineReader(self.connection)
        self.rfile = io.BufferedReader(self._reader)

    def handle_one_request(self) -> None:
        # the base class answers a TimeoutError from any read by dropping the connection, as for a stalled client
        self._reader.deadline = time.monotonic() + self.timeout
        super().handle_one_request()

    def parse_request(self) -> bool:
        if len(self.raw_requestline.split()) == 2:
            # HTTP/0.9's "GET /", no version: the base class would go on to read headers such a client never sends,
            # holding a connection slot until the request timeout. Answered at once, as HTTP/1.0 answers.
            self.command, self.request_version = "", self.default_request_version
            self.requestline = str(self.raw_requestline, "iso-8859-1").rstrip("\r\n")
            self._send(HTTPStatus.HTTP_VERSION_NOT_SUPPORTED, _TEXT, b"HTTP/0.9 is not served: send HTTP/1.0 or 1.1\n")
            return False
        if not super().parse_request():  # it has answered the error
            return False
        if self.command not in ("GET", "HEAD"):  # rather than the base class's 501 for methods with no do_*
            self._send(HTTPStatus.METHOD_NOT_ALLOWED, "text/plain; charset=utf-8",
                       f"method not allowed: {self.command}\n".encode(), {"Allow": "GET, HEAD"})
            return False
        return True

    def version_string(self) -> str:
        return self.server_version  # the base class appends Python's version

    def end_headers(self) -> None:
        # every answer, the base class's own errors too: a browser must not read a body that echoes the path
        # (a 404's) as HTML or script
        self.send_header("X-Content-Type-Options", "nosniff")
        super().end_headers()

    def do_GET(self) -> None:  # noqa: N802 (http.server's naming)
        try:
            path = urlsplit(self.path).path
        except ValueError as exc:  # e.g. "GET http://[x/": not a URL
            self._send(400, "text/plain; charset=utf-8", f"bad request path: {exc}\n".encode())
            return
        self._send(*self.dashboard.answer(path))

    do_HEAD = do_GET  # noqa: N815 (the same headers; _send leaves the body out)

    def _send(self, status: int, ctype: str, body: bytes, headers: dict[str, str] | None = None) -> None:
        self.send_response(status)
        self.send_header("Content-Type", ctype)
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Cache-Control", "no-store")
        for name, value in (headers or {}).items():
            self.send_header(name, value)
        self.end_headers()
        if self.command != "HEAD":
            self.wfile.write(body)

    def log_message(self, format: str, *args: Any) -> None:  # noqa: A002 (signature of the base class)
        log.debug("dashboard: " + format, *args)


@functools.cache  # thread-safe: two first requests at once may both draw it, both get the same bytes
def _placeholder_png() -> bytes:
    """A small image for when there is nothing to draw (no champion, its weights cannot be loaded, no eval split
    pinned), so the page's <img> never 404s; the cards above it say which."""
    from matplotlib.figure import Figure  # start-up cost (0.15-0.4 s for every command), not a cycle
    fig = Figure(figsize=(4, 0.6), dpi=80)
    fig.text(0.5, 0.5, "no champion loaded to draw", ha="center", va="center", color="#888")
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    return buf.getvalue()


# -- sources over a data directory ------------------------------------------------------------

def newest_model(registry: ModelRegistry) -> dict | None:
    """The last retrain as the registry knows it, for a process that ran none itself (a standalone dashboard, a
    service restarted since, retrains by system cron): its newest model, ``"from": "registry"``; None when
    there is none."""
    newest = registry.newest()
    if newest is None:
        return None
    return {"status": newest.status.value, "version": newest.version, "reason": newest.reason,
            "finished": newest.created, "from": "registry"}


@dataclass
class DataSources:
    """``DashboardSources`` read from a data directory (its stores opened for each read and closed after).

    ``workers``, ``metrics_text``, ``retrains`` and ``frames_png`` come from the running
    service when there is one; ``budget`` is the run's episode budget (0 = none). Without a
    service's ``metrics_text``, ``/metrics`` gives only the gauges the data directory holds (queue
    depth, episodes, champion, disk; ``metrics.STORE_GAUGES``): this process counts nothing, and
    knows no workers.
    """

    data_dir: Path
    workers: Callable[[], list[dict]] | None = None
    """The live workers; None (no service here) leaves ``workers_alive`` unknown (null), not 0."""
    metrics_text: Callable[[], str] | None = None
    retrains: Callable[[], list[dict]] = lambda: []
    frames_png: Callable[[], bytes] = lambda: b""
    budget: int = 0
    gauges: ServiceMetrics = field(default_factory=ServiceMetrics)
    """The store gauges ``/metrics`` shows without a service, kept between requests: the space of
    ``DATA/quarantine/`` is walked again only every ``metrics.QUARANTINE_WALK_S``, not per request."""

    @contextmanager
    def _stores(self) -> Iterator[tuple[Catalog, RequestQueue, ModelRegistry]]:
        """The data directory's stores for one read, the queue's connections closed after it: http.server runs
        each connection on a new thread, so stores kept per thread held their files open until the GC ran.
        CatalogError when the catalog is not there (the directory moved, removed, its disk unmounted): opening
        the stores would make a new empty one, and the page would show an empty fleet. The catalog makes no
        ``episodes/`` folder, nor the registry ``models/``, where there is none (no episode ingested, no model
        trained yet): the dashboard writes nothing."""
        self._refuse_lost()
        catalog = Catalog(self.data_dir, make_episodes_dir=False)
        with RequestQueue(catalog.db_path, busy_timeout_s=READ_BUSY_TIMEOUT_S) as queue:
            yield catalog, queue, ModelRegistry(self.data_dir, make_models_dir=False)

    def _refuse_lost(self) -> None:
        if not (Path(self.data_dir) / DB_NAME).is_file():
            raise CatalogError(f"no catalog at {self.data_dir}: was the data directory moved or removed, or its "
                               f"disk unmounted? (the dashboard only reads; it creates none)")

    def _frames(self) -> bytes:
        """``frames_png``, checked as ``_stores`` is: the champion's loader opens the registry, which would make the
        lost data directory anew."""
        self._refuse_lost()
        return self.frames_png()

    def sources(self) -> DashboardSources:
        return DashboardSources(stats=self.stats, queue=self.queue, workers=self.workers or list, models=self.models,
                                curve=self.curve, metrics_text=self.metrics_text or self.data_metrics,
                                frames_png=self._frames)

    def data_metrics(self) -> str:
        """Prometheus text of the gauges read from the data directory (a dashboard without a service)."""
        with self._stores() as (catalog, queue, registry):
            self.gauges.read_stores(queue, catalog, registry)
        return self.gauges.render_stores()

    def stats(self) -> dict:
        with self._stores() as (catalog, queue, registry):
            champion = registry.champion()
            h1 = registry.get(champion).metrics.get("h1_mse") if champion else None
            problem = registry.weights_problem(champion) if champion else None
            episodes = {"train": catalog.count(split="train"), "eval": catalog.count(split="eval"),
                        "quarantined": catalog.count(quarantined=True)}
            counts = queue.counts()
            retrains = self.retrains()
            last = retrains[-1] if retrains else newest_model(registry)
        return {"episodes": episodes, "quarantine_bytes": self.gauges.quarantine_space.read(self.data_dir),
                "budget": self.budget, "queue": counts,
                "workers_alive": None if self.workers is None else len(self.workers()),
                "champion": champion, "champion_h1_mse": h1, "champion_problem": problem,
                "disk": disk_json(self.data_dir),
                "retrains": len(retrains), "last_retrain": last}

    def queue(self, rows: int) -> dict:
        with self._stores() as (_, queue, _):
            latest = queue.list(limit=rows)
            counts = queue.counts()
        return {"counts": counts, "requests": [request_json(r) for r in latest]}

    def models(self) -> dict:
        with self._stores() as (_, _, registry):
            champion = registry.champion()
            listed = registry.list()
        models = []
        for m in listed:
            d = m.to_json()
            d.pop("config", None)
            models.append(d)
        return {"champion": champion, "models": models}

    def curve(self) -> list[dict]:
        with self._stores() as (catalog, _, registry):
            return learning_curve(catalog, registry)


def request_json(r: Any) -> dict:
    """The fields of a queued request the dashboard shows."""
    return {"id": r.id, "status": getattr(r.status, "value", r.status), "priority": r.priority,
            "shape": r.shape, "policy": r.policy, "reason": r.reason, "attempts": r.attempts,
            "last_error": r.last_error, "created": r.created}


def learning_curve(catalog: Catalog, registry: ModelRegistry) -> list[dict]:
    """Eval error of every registered model against the training episodes it saw, oldest first."""
    points = []
    history = registry.history()
    live = {e.version for e in history if e.rolled_back_at is None}   # promotions that stand
    withdrawn = {e.version for e in history} - live                    # every promotion of it rolled back
    for m in sorted(registry.list(), key=lambda m: m.version):
        episodes = m.metrics.get("train_episodes")
        if episodes is None:  # models trained elsewhere: count what the catalog held when it was made
            episodes = _episodes_before(catalog, m.created)
        points.append({"version": m.version, "episodes": int(episodes), "status": m.status.value,
                       "promoted": m.version in live or m.status.value == "champion",
                       "rolled_back": m.version in withdrawn and m.status.value != "champion",
                       "h1_mse": m.metrics.get("h1_mse"), "h5_mse": m.metrics.get("h5_mse"),
                       "baseline_h1_mse": m.metrics.get("baseline_h1_mse"),
                       "baseline_h5_mse": m.metrics.get("baseline_h5_mse")})
    return points


def _episodes_before(catalog: Catalog, created: str) -> int:
    """Training episodes indexed before ``created`` (ISO 8601): by the catalog's ingest time, not the episode's
    own ``created``, which is when and by whose clock it was collected (one collected elsewhere long ago and
    ingested after the model was made was no part of what the model could see)."""
    return catalog.count(split="train") - catalog.count(split="train", since=created)
