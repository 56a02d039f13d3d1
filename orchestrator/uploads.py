"""The upload path of the service: verify an episode, store it once, complete its request.

``UploadHandler.handle`` answers ``NS/orch/upload`` (an ``UploadHeader`` attachment and the
MCAP bytes). It checks the lease (token and worker) before a byte is written, the size and
the sha256, verifies the MCAP once, then writes the file atomically, indexes it and completes
the request in one catalog transaction. A repeat of an upload that already completed its
request is acknowledged as a duplicate once the catalog holds an intact copy of those bytes: a file lost or
damaged on disk since is put back from the repeat's, or, for an episode quarantined meanwhile, the repeat's
bytes are kept in quarantine (``Catalog.repair_file``: a worker's retry never ends a quarantine, nor does a copy
sent before the first reply came back that finds its episode indexed: ``ingest_bytes(readmit=False)``); anything
else that does not fit is refused with the reason, and nothing of it is indexed. A write the storage refuses
for a reason that passes (a full disk, a lock held past the busy timeout, a read-only file system) is
the service's ``StorageHealth``'s to know (no lease expires meanwhile) and the worker's to send again
(``unavailable``); one that does not pass is ``internal``, never ``bad_field``, which is for the
upload's own content only. Stored episodes are handed to ``on_stored`` (the service's background
thread: scoring and planning never run on this path). An upload sent in parts (``orchestrator.upload_parts``)
takes this path once its last part has come, with its bytes whole.

An episode of another frame size than the catalog's is refused ``bad_field`` from its metadata, before a chunk is
inflated (its upload is bounded by the catalog's size). Under a lease granted without a frame size
(``UploadHandler.sizeless``: a worker from before ``image_size``, whose lease request gives none, or any worker
while the catalog held no episode), whose worker recorded at its own size as its grant allowed, the refusal says
what to do and comes after the request was given back with no attempt counted: the worker's ``fail`` is stale.
Such an older worker, refused for its size, is then refused its leases (``check_lease``: nothing it collects could be
stored) until it says its size (an upgraded worker) or its liveliness token comes or goes (``forget_worker``: a
restart, perhaps at the catalog's size).
"""

from __future__ import annotations

import logging
import math
import threading
from collections import OrderedDict
from collections.abc import Callable
from contextlib import AbstractContextManager
from dataclasses import dataclass
from typing import Any

import numpy as np

from orchestrator import admin, messages, protocol
from orchestrator.bounded import remember
from orchestrator.metrics import ServiceMetrics
from orchestrator.protocol import ErrorCode, EventKind, ProtocolError
from orchestrator.storagehealth import StorageHealth
from orchestrator.transport import Incoming
from orchestrator.upload_parts import PartStaging
from storage.catalog import Catalog
from storage.episode_reader import EpisodeInfo, decoded_limit, read_episode
from storage.errors import (EpisodeError, FrameSizeError, OversizedEpisodeError, QueueError, StaleLeaseError,
                            StorageError, StorageUnavailableError)
from storage.files import holds
from storage.queue import RequestQueue
from storage.records import Episode
from storage.requests import IllegalTransitionError, Request, RequestStatus
from storage.rows import EpisodeRow
from workers.env import resolve_physics

log = logging.getLogger(__name__)

SIZELESS_MAX = 4096
"""The most leases granted without a frame size (and older workers refused for theirs) the upload path keeps in
memory: the oldest are forgotten first (an upload of a forgotten one is bounded and checked as any other; a
forgotten worker is leased to again, and refused for its size again)."""


@dataclass(frozen=True)
class StoredEpisode:
    """An episode a worker uploaded and the service stored, as the background callbacks get it."""

    episode_id: str
    """Catalog id of the episode."""
    request_id: str
    """The request it completed."""
    worker_id: str
    """The worker that collected it."""
    episode: Episode
    """The decoded episode (frames, actions, states, provenance)."""


class UploadHandler:
    """Stores uploaded episodes exactly once; see the module docstring."""

    def __init__(self, queue: RequestQueue, catalog: Catalog, metrics: ServiceMetrics,
                 publish: Callable[[EventKind, dict[str, Any]], None],
                 turn: Callable[[], AbstractContextManager[None]],
                 max_upload_bytes: int, on_stored: Callable[[StoredEpisode], None],
                 frame_size: Callable[[], int] = lambda: 0, *, health: StorageHealth,
                 parts_max_age_s: float = 60.0, parts_max_bytes: int | None = None) -> None:
        self.queue = queue
        self.catalog = catalog
        self.metrics = metrics
        self.publish = publish
        self.turn = turn
        """The service's writer turn (``Service._writing``), which the ingest transaction takes like every queue
        transition: a write it refuses for a reason that passes is ``health``'s to know before the turn passes
        on (else a reap that took it in between expired the leases nobody could renew)."""
        self.health = health
        """The service's: a write of an upload the storage refuses holds every lease, as a renew's does."""
        self.max_upload_bytes = max_upload_bytes
        self.on_stored = on_stored
        self.frame_size = frame_size
        """The catalog's frame size (0 while unknown): bounds what an upload may inflate to."""
        self.parts = PartStaging(parts_max_age_s, live=self._lease_live,
                                 max_total_bytes=4 * max_upload_bytes if parts_max_bytes is None else parts_max_bytes)
        metrics.upload_parts_held_bytes.set_function(self.parts.held_bytes)
        """Uploads sent in parts, held until their last part (``orchestrator.upload_parts``)."""
        self._sizeless: OrderedDict[tuple[str, int], bool] = OrderedDict()
        """(request id, token) of each lease granted without a frame size: whether its worker is an older one."""
        self._older: OrderedDict[str, tuple[int, int]] = OrderedDict()
        """The older workers whose frame size was refused: (theirs, the catalog's). Warned of once each; their leases
        are refused until they say their size or their liveliness token comes or goes."""
        self._sizeless_lock = threading.Lock()

    def sizeless(self, request_id: str, token: int, *, older: bool = True) -> None:
        """Remember a lease whose grant named no frame size, so its worker records at its own: ``older``, one from
        before ``image_size`` (its lease request gave none), else the catalog held no episode when it was granted.
        An upload of another size than the catalog's is refused and its request given back uncharged
        (``_check_size``). The newest ``SIZELESS_MAX`` are kept."""
        with self._sizeless_lock:
            remember(self._sizeless, (request_id, token), older, SIZELESS_MAX)

    def check_lease(self, worker_id: str, image_size: int) -> None:
        """A lease request of ``worker_id`` giving ``image_size`` (0: none): refused (ProtocolError ``bad_field``)
        from an older worker whose upload was refused for its frame size, before it collects another that would be;
        one that says its size is an upgraded worker, forgotten."""
        if not self._older:  # (the hot path: no such worker)
            return
        with self._sizeless_lock:
            sizes = self._older.pop(worker_id, None) if image_size else self._older.get(worker_id)
        if sizes is not None and not image_size:
            found, holds = sizes
            raise ProtocolError(ErrorCode.BAD_FIELD, f"worker {worker_id} records {found}px frames; this catalog holds "
                                f"{holds}px episodes, and its upload was refused for that. It does not say its size "
                                f"when it asks for a lease (a worker from before image_size), so it gets none until "
                                f"it restarts: upgrade it or start it with --size {holds}")

    def forget_worker(self, worker_id: str) -> None:
        """``worker_id``'s liveliness token came or went (a restart, perhaps at another size): it may lease again."""
        with self._sizeless_lock:
            self._older.pop(worker_id, None)

    def _unsized(self, header: messages.UploadHeader) -> bool | None:
        """Whether the lease ``header`` uploads under was granted without a frame size to an older worker (True) or
        while the catalog's size was unknown (False); None: it named one (or was forgotten)."""
        with self._sizeless_lock:
            return self._sizeless.get((header.request_id, header.token))

    def _forget(self, header: messages.UploadHeader) -> None:
        with self._sizeless_lock:
            self._sizeless.pop((header.request_id, header.token), None)

    def handle(self, msg: Incoming) -> bytes:
        """Answer one ``NS/orch/upload`` query: store the episode and complete its request, or refuse.

        Every refusal, whichever check raised it (the header, the request, the size, the hash, the
        lease, the episode, the catalog), is counted ``uploads_total{result="refused"}`` and published
        as ``episode.rejected`` here, once, so both agree with the service's ``refusals_total``: it
        answers a ProtocolError with its code and anything else as ``internal``, and this re-raises
        both. Raises ProtocolError for a refused upload.
        """
        header: messages.UploadHeader | None = None
        try:
            header = messages.upload_header(msg.attachment)
            if isinstance(header, messages.UploadPart):
                return self._part(msg.payload, header)
            return self._store(msg.payload, header)
        except ProtocolError as exc:
            self._refused(header, exc.code.value, exc.message)
            raise
        except Exception as exc:  # noqa: BLE001 -- counted and raised on: the service answers it "internal"
            self._refused(header, ErrorCode.INTERNAL.value, f"{type(exc).__name__}: {exc}")
            raise

    def _request(self, header: messages.UploadHeader, payload: bytes) -> Request:
        """The request ``header`` uploads for; refused when it or the upload is too big for this service."""
        try:
            request = self.queue.get(header.request_id)
        except QueueError as exc:
            raise admin.protocol_error(exc) from exc
        if header.size > self.max_upload_bytes or len(payload) > self.max_upload_bytes:
            raise ProtocolError(ErrorCode.TOO_LARGE, f"payload: expected at most {self.max_upload_bytes} "
                                f"bytes, found {max(header.size, len(payload))}")
        return request

    def _lease_live(self, header: messages.UploadHeader) -> bool:
        """Whether the lease ``header`` uploads under is still live (``PartStaging.sweep`` keeps its parts)."""
        try:
            request = self.queue.get(header.request_id)
        except QueueError:  # unknown: gone
            return False
        except StorageError:  # cannot tell now: keep them until the next sweep
            return True
        return _under(request, header, RequestStatus.LEASED)

    def _part(self, payload: bytes, part: messages.UploadPart) -> bytes:
        """One part of an upload in parts: kept for the lease's holder; the last one stores the whole."""
        whole = part.whole()
        request = self._request(whole, payload)
        row = self._duplicate_of(request, whole)
        if row is not None and not row.quarantined and holds(row.path, row.sha256):  # the stored copy is intact
            self.parts.drop(whole)  # (else the whole bytes again restore it, as a whole upload's repeat does)
            self.metrics.upload("duplicate")
            return protocol.duplicate_reply(request_id=request.id, episode_id=request.episode_id)
        if row is None:
            try:
                self._check_live(request, whole)  # before a byte is kept
                most = self._most_bytes(request)
                if whole.size > most:  # no episode of this request is that big: hold nothing
                    raise ProtocolError(ErrorCode.TOO_LARGE, f"size: expected at most {most} bytes for "
                                        f"{len(request.action_prefix) + request.steps} steps, found {whole.size}")
            except ProtocolError:
                self.parts.drop(whole)
                raise
        got = self.parts.add(part, payload)
        if isinstance(got, int):
            return protocol.ok_reply(request_id=request.id, received=got)
        try:
            reply = self._store(got, whole)
        except ProtocolError as exc:
            if exc.code not in (ErrorCode.UNAVAILABLE, ErrorCode.INTERNAL):  # else the last part again stores them
                self.parts.drop(whole)
            raise
        self.parts.drop(whole)
        return reply

    def _store(self, payload: bytes, header: messages.UploadHeader) -> bytes:
        request = self._request(header, payload)
        data = header.check_payload(payload)  # a repeat too: it is acknowledged for these bytes
        row = self._duplicate_of(request, header)
        if row is not None:  # e.g. the reply was lost and the worker sends it again
            self._restore_if_lost(row, data, header)  # before the worker lets go of its bytes
            self.metrics.upload("duplicate")
            return protocol.duplicate_reply(request_id=request.id, episode_id=request.episode_id)
        self._check_live(request, header)  # before a byte is written
        episode = self._decode(data, header, request)  # the one full read of the bytes; ingest reuses it
        try:
            with self.health.writing():
                result = self.catalog.ingest_bytes(
                    data, expected_sha256=header.sha256, split="train",
                    in_transaction=lambda conn: self.queue.complete(
                        header.request_id, header.token, episode.meta.episode_id, conn,
                        worker_id=header.worker_id),
                    verified=EpisodeInfo(meta=episode.meta, frames=len(episode)), write_lock=self.turn(),
                    readmit=False)  # a racing copy of the first upload keeps a quarantine committed since
        except (StaleLeaseError, IllegalTransitionError) as exc:
            request = self.queue.get(header.request_id)  # a racing identical upload may have won
            if self._duplicate_of(request, header) is not None:
                self.metrics.upload("duplicate")
                return protocol.duplicate_reply(request_id=request.id, episode_id=request.episode_id)
            raise admin.protocol_error(exc) from exc
        except EpisodeError as exc:
            raise ProtocolError(ErrorCode.CORRUPT_EPISODE, str(exc)) from exc
        except StorageError as exc:  # nothing stored
            code = _ingest_refusal(exc)
            if code == ErrorCode.BAD_FIELD:  # a size fixed since it was read (a racing upload, another process)?
                self._check_size(request, header, episode.meta.image_size, self._catalog_size())
            raise ProtocolError(code, str(exc)) from exc
        self._forget(header)
        if result.duplicate:  # indexed before: by a racing identical upload, or for another request
            if self._duplicate_of(self.queue.get(header.request_id), header) is not None:
                self.metrics.upload("duplicate")
                return protocol.duplicate_reply(request_id=header.request_id, episode_id=result.episode_id)
            raise ProtocolError(ErrorCode.BAD_FIELD, f"episode {result.episode_id} is already "
                                "in the catalog for another request")
        self.metrics.upload("stored")
        self.publish(EventKind.REQUEST_DONE, {"request_id": header.request_id, "worker_id": header.worker_id,
                                              "episode_id": result.episode_id})
        self.publish(EventKind.EPISODE_STORED, {"episode_id": result.episode_id, "request_id": header.request_id,
                                                "shape": episode.meta.shape, "frames": len(episode)})
        self.on_stored(StoredEpisode(result.episode_id, header.request_id, header.worker_id, episode))
        return protocol.ok_reply(request_id=header.request_id, episode_id=result.episode_id)

    def _duplicate_of(self, request: Request, header: messages.UploadHeader) -> EpisodeRow | None:
        """The row of the episode that completed ``request`` when this is a repeat of that upload (same token,
        same worker, same bytes); None otherwise. Another worker's copy of those bytes is no repeat: it held no
        such lease, and ``_check_live`` refuses it as stale rather than telling it they were stored for it."""
        if not _under(request, header, RequestStatus.DONE) or not request.episode_id:
            return None
        row = self.catalog.find(request.episode_id)
        return row if row is not None and row.sha256 == header.sha256 else None

    def _restore_if_lost(self, row: EpisodeRow, data: bytes, header: messages.UploadHeader) -> None:
        """Before a repeat is acknowledged: when the catalog no longer holds an intact copy of the episode's
        bytes (its file lost or damaged on disk, and for a quarantined episode no intact copy kept in
        quarantine either), ``data`` (its sha256 is the row's) is kept (``Catalog.repair_file``): the file is
        put back, or, for a quarantined episode, the bytes are kept in quarantine for ``episodes restore``. A
        quarantine (an operator's or a training job's decision) is not ended by a worker's retry, not even one
        that commits while this repeat is checked. Refused ``unavailable`` when the bytes cannot be written (a
        full disk), so the worker keeps them and sends them again."""
        if not row.quarantined and holds(row.path, row.sha256):  # the common case, without the write lock
            return
        try:
            with self.health.writing():
                written = self.catalog.repair_file(row.episode_id, data, write_lock=self.turn())
        except StorageError as exc:  # the bytes hash to a verified episode's: the disk, not the upload
            code = ErrorCode.UNAVAILABLE if isinstance(exc, StorageUnavailableError) else ErrorCode.INTERNAL
            raise ProtocolError(code, f"episode {row.episode_id}: its file does not hold the bytes "
                                f"indexed, and restoring it from this upload failed: {exc}") from exc
        if written is not None:
            log.warning("episode %s: its file %s was missing or damaged; %s written from a repeated upload of %s",
                        row.episode_id, row.path, written, header.request_id)

    def _check_live(self, request: Request, header: messages.UploadHeader) -> None:
        if _under(request, header, RequestStatus.DONE):  # (the same bytes again were a duplicate, answered)
            log.error("two workers use the id %s: both collected %s under its lease (token %d) and uploaded other "
                      "bytes; every request is collected twice: give each worker its own --id",
                      header.worker_id, request.id, header.token)
            raise ProtocolError(
                ErrorCode.STALE_TOKEN, f"upload {request.id}: another worker with the id {header.worker_id} "
                f"has already uploaded other bytes for this lease (token {header.token}); two workers share the "
                f"id {header.worker_id}: give each its own --id")
        if not _under(request, header, RequestStatus.LEASED):
            raise ProtocolError(
                ErrorCode.STALE_TOKEN, f"upload {request.id}: expected the live lease, found token "
                f"{header.token} from {header.worker_id} while the request is {request.status.value} "
                f"with token {request.token} held by {request.worker_id}")

    def _decode(self, data: bytes, header: messages.UploadHeader, request: Request) -> Episode:
        try:
            episode = read_episode(data, name=f"upload for {header.request_id}",  # no more than the request needs
                                   max_decoded=self._most_bytes(request), frame_size=self.frame_size())
        except FrameSizeError as exc:  # from its metadata, before a chunk is inflated
            self._check_size(request, header, exc.found, exc.expected)  # (a lease that named no size)
            raise ProtocolError(ErrorCode.BAD_FIELD, f"upload {request.id}: {exc.found}px frames; this catalog holds "
                                f"{exc.expected}px episodes (the size each lease names to a worker that says its own; "
                                f"a worker from before image_size: start it with --size {exc.expected})") from exc
        except OversizedEpisodeError as exc:
            raise ProtocolError(ErrorCode.TOO_LARGE, str(exc)) from exc
        except EpisodeError as exc:
            raise ProtocolError(ErrorCode.CORRUPT_EPISODE, str(exc)) from exc
        mismatch = provenance_mismatch(episode, request, header.worker_id)
        if mismatch:
            raise ProtocolError(ErrorCode.BAD_FIELD, f"episode provenance: {mismatch}")
        return episode

    def _most_bytes(self, request: Request) -> int:
        """The most bytes an episode of ``request`` may inflate to: also the most its file may hold (compression
        never grows it past the per-step margin), so an upload in parts declaring more is refused before its
        first part is kept."""
        return decoded_limit(len(request.action_prefix) + request.steps, self.frame_size() or protocol.MAX_FRAME_SIZE)

    def _catalog_size(self) -> int:
        """The catalog's frame size read now (0: none yet, or it cannot be read: the catalog's refusal stands)."""
        try:
            return self.catalog.frame_size() or 0
        except StorageError:
            return 0

    def _check_size(self, request: Request, header: messages.UploadHeader, found: int, holds: int) -> None:
        """Refuse (``bad_field``) an episode of ``found`` px under a lease granted without a frame size when the
        catalog holds ``holds`` px, once its request is given back with no attempt counted: its worker recorded
        at its own size, as its grant said, and the request did nothing wrong (charged, a few such workers would
        kill every request). Under a lease that named the size, the caller refuses it as its worker's fault."""
        older = self._unsized(header)
        if older is None or not holds or found == holds:
            return
        released = self._give_back(request, header)
        self._forget(header)
        worker = header.worker_id
        if older:
            self._mark_older(worker, found, holds)
            why = (f"worker {worker} records {found}px frames; this catalog holds {holds}px episodes. It does not say "
                   f"its size when it asks for a lease (a worker from before image_size), so it cannot be told "
                   f"the catalog's: upgrade it or start it with --size {holds}")
        else:
            why = (f"worker {worker} recorded {found}px frames, its own size: its lease was granted while the catalog "
                   f"held no episode, and it holds {holds}px episodes since (its next lease names that size)")
        raise ProtocolError(ErrorCode.BAD_FIELD, f"upload {request.id}: {why}; " + (
            "the request is queued again, no attempt counted" if released else "its lease had ended already"))

    def _give_back(self, request: Request, header: messages.UploadHeader) -> bool:
        """Queue ``request`` again, no attempt counted, before the refusal is answered; False when its lease had
        ended. Raises ProtocolError ``unavailable`` when the queue cannot be written now (the worker sends the
        upload again, and it is refused then)."""
        try:
            release_lease(self.queue, self.turn, self.publish, request.id, header.token, header.worker_id)
        except StaleLeaseError:  # expired or ended meanwhile: nothing to give back
            return False
        except StorageError as exc:
            raise admin.protocol_error(exc) from exc
        return True

    def _mark_older(self, worker_id: str, found: int, holds: int) -> None:
        """An older worker of another frame size: its leases are refused from now on (``check_lease``), and the
        service log says so once while it is marked, not once per upload."""
        with self._sizeless_lock:
            known = worker_id in self._older
            remember(self._older, worker_id, (found, holds), SIZELESS_MAX)
        if not known:
            log.warning("worker %s records %dpx frames, not this catalog's %dpx, and is from before workers say their "
                        "size: its upload was refused and its request queued again (no attempt counted), and its "
                        "lease requests are refused until it restarts; upgrade it or start it with --size %d",
                        worker_id, found, holds, holds)

    def _refused(self, header: messages.UploadHeader | None, code: str, message: str) -> None:
        """Count and publish one refused upload (``header`` None: it was malformed, so whose is unknown)."""
        self.metrics.upload("refused")
        self.publish(EventKind.EPISODE_REJECTED, {
            "request_id": header.request_id if header is not None else None,
            "worker_id": header.worker_id if header is not None else None,
            "error": code, "message": message[:500]})


def release_lease(queue: RequestQueue, turn: Callable[[], AbstractContextManager[None]],
                  publish: Callable[[EventKind, dict[str, Any]], None], request_id: str, token: int,
                  worker_id: str) -> Request:
    """Give the request ``request_id`` leased under ``token`` back to the queue, no attempt counted, in the writer's
    ``turn``, and announce it (a worker's ``release``, or an upload refused for its size). Raises ``QueueError``
    (``StaleLeaseError``: the lease has ended)."""
    with turn():
        after = queue.release(request_id, token, worker_id=worker_id)
    publish(EventKind.REQUEST_RELEASED, {"request_id": after.id, "worker_id": worker_id, "token": token,
                                         "status": after.status.value, "attempts": after.attempts})
    return after


def _under(request: Request, header: messages.UploadHeader, status: RequestStatus) -> bool:
    """Whether ``request`` is in ``status`` under the lease ``header`` names (its token, its worker)."""
    return request.status == status and request.token == header.token and request.worker_id == header.worker_id


def _ingest_refusal(exc: StorageError) -> ErrorCode:
    """The wire code of an upload the catalog did not store. ``bad_field`` only for a refusal of the upload itself
    (its id indexed with other bytes, a frame size the catalog refuses, a replay of an eval episode), on which
    the worker fails the request and drops its episode; the disk or the database failing under it is
    ``admin.storage_failure``'s (``unavailable`` or ``internal``), on which the worker sends the same bytes again."""
    return admin.storage_failure(exc) or ErrorCode.BAD_FIELD


def provenance_mismatch(episode: Episode, request: Request, worker_id: str) -> str:
    """Why ``episode`` is not what ``request`` asked ``worker_id`` for ('' when it is).

    An upload completes its request and enters the catalog (and the planner's view) with its
    metadata, so the metadata must say what was asked: the request, the worker, the task,
    shape and policy, the start state and policy parameters the request gave (the worker may
    add the defaults it filled in), the action prefix and the number of steps, the lease's seed,
    and physics inside the task space that hold what the request asked.
    """
    meta, prefix = episode.meta, request.action_prefix
    expected = {"request_id": request.id, "worker_id": worker_id, "task": request.task, "shape": request.shape,
                "policy": request.policy, "action_prefix_len": len(prefix)}
    for key, want in expected.items():
        if getattr(meta, key) != want:
            return f"expected {key} {want!r}, found {getattr(meta, key)!r}"
    if len(episode) != len(prefix) + request.steps:
        return f"expected {len(prefix)} prefix + {request.steps} steps, found {len(episode)} frames"
    if prefix and not np.allclose(episode.actions[:len(prefix)], np.asarray(prefix, np.float64),
                                  rtol=1e-6, atol=1e-3):  # stored as float32
        return "the episode's first actions are not the request's action prefix"
    seed = messages.request_seed(request.id, request.token)
    if meta.seed != seed:
        return f"expected the lease's seed {seed}, found {meta.seed!r}"
    problem = protocol.episode_problem(meta)
    if problem:
        return problem
    physics = resolve_physics(request.start_state.get("physics"))  # what the worker ran: defaults filled in
    for name, asked, found in (("start_state", request.start_state, meta.start_state),
                               ("policy_params", request.policy_params, meta.policy_params),
                               ("physics", physics, meta.physics)):
        where = _differs(asked, found, name)
        if where:
            return f"{where} differs from the request's"
    return ""


def _differs(asked: Any, found: Any, path: str) -> str:
    """The first place where ``found`` does not hold ``asked`` (dicts: asked's keys only; numbers: close)."""
    if isinstance(asked, dict):
        if not isinstance(found, dict):
            return path
        return next((w for k, v in asked.items() if (w := _differs(v, found.get(k), f"{path}.{k}"))), "")
    if isinstance(asked, (list, tuple)):
        if not isinstance(found, (list, tuple)) or len(found) != len(asked):
            return path
        return next((w for i, (a, f) in enumerate(zip(asked, found)) if (w := _differs(a, f, f"{path}[{i}]"))), "")
    if isinstance(asked, (int, float)) and not isinstance(asked, bool):
        ok = isinstance(found, (int, float)) and not isinstance(found, bool) and math.isclose(
            asked, found, rel_tol=1e-9, abs_tol=1e-9)
        return "" if ok else path
    return "" if asked == found else path
