"""The worker agent: lease a collection request over Zenoh, collect it, upload the MCAP.

Loop (``Worker.run``)::

    lease -> reset the simulator to the start state, replay the action prefix, run the policy
          -> encode MCAP (the request id in its provenance) -> upload -> next

While an episode is being collected a background timer renews the lease every
``lease_s / 3`` (by the clock; one renewal waits at most that long). Transient
failures (nobody answers: the service is restarting or unreachable; an upload
answered ``internal`` or ``unavailable``, or with a reply it cannot read:
``read_reply``) are retried with exponential backoff,
an upload until it is acknowledged or the lease is lost. Real failures are
reported with ``fail``, which counts an attempt: the collection raised (for
instance the request names a policy parameter this worker does not know --
``policy_params: {"fail": true}`` is such a request, the documented way to
make a *poison* request that fails on every worker), or the service refused
the upload as corrupt. A lease that is no longer ours (the service says
``stale_token``) is dropped without a word: someone else owns the request now.
An episode bigger than ``WorkerConfig.part_bytes`` is uploaded in parts, each
answered before the next goes (``workers.upload``); a retry goes on from the
last part the service holds.

SIGTERM / SIGINT drain: the current request is finished and uploaded, then
the worker exits. The upload is then tried for one more lease term at most: an
episode never acknowledged (held in memory only) is dropped, and the service
queues the request again -- when nobody answers, once the lease has run out by
the worker's clock (the service is gone: exit 0); when a live service would not
store it (``unavailable``: a full disk), after that term, giving the request
back (exit 1: collected work was lost). A failure reported once a stop was
asked gets one try of at most ``STOPPING_TIMEOUT_S`` (unanswered: the lease
runs out on its own). A second signal drops the current episode at once, in
the middle of its collection too, and gives the request back (``release``:
queued again, no attempt counted -- the request did nothing wrong; a query in
flight is walked away from, the release waits at most ``STOPPING_TIMEOUT_S``,
unanswered the lease runs out), and the worker exits 1 (``abandoned`` says what
it dropped; nothing acknowledged is lost). ``DRAIN_SIGNAL`` drains too and
never counts as a stop signal: ``activecollect run`` stops its workers with it,
as systemd or ``kill -TERM -PGID`` may have sent them SIGTERM already. A worker
of ``run`` is also sent SIGTERM when ``run`` dies (its parent-death signal),
which the kernel may send more than once (once per thread of ``run`` that
inherits the child as it exits): the worker then gives its request back at
once, which is right there, since the service died with ``run``.
A request granted after the drain began (its lease query was in flight) is not
in hand: it is given back unstarted (``release``). Run as ``python -m
workers.agent``, it takes these signals from before its imports on
(``workers.startup``): one that comes while it starts ends it, exit 0.

Imports only ``storage``, ``workers``, ``orchestrator.protocol``, ``orchestrator.messages``,
``orchestrator.transport`` and ``orchestrator.endpoints`` -- the wire contract -- and
``orchestrator.signals``, so it runs on any host.
"""

from __future__ import annotations

if __name__ == "__main__":  # ``python -m workers.agent``: before the imports below, which take a second or so
    from workers import startup
    startup.guard()

import logging
import random
import sys
import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np
import zenoh

from orchestrator import messages, protocol, signals, transport
from orchestrator.messages import LeaseGrant
from orchestrator.protocol import ErrorCode, Keys, ProtocolError
from storage.episodes import encode_episode
from workers.abandon import Abandoned, Abandoner
from workers.collect import CollectionStopped, collect_episode
from workers.env import CONTROL_HZ
from workers.lease import Renewer
from workers.config import WorkerConfig, WorkerError
from workers.startup import DRAIN_SIGNAL
from workers.upload import EpisodeUpload

log = logging.getLogger("workers.agent")  # also when run as __main__

#: Longest wait for one reply once a stop was asked (a release, a failure report): a supervisor's grace is short.
STOPPING_TIMEOUT_S = 2.0
#: Shortest wait for an upload's reply while draining (each is cut to what is left: ``Renewer.drain_left``).
MIN_DRAIN_ATTEMPT_S = 0.5
#: How often a paced episode (``--realtime``) looks whether its lease was lost meanwhile.
PACE_CHECK_S = 0.5


def read_reply(data: bytes) -> dict[str, Any]:
    """``protocol.parse_reply``, except that a reply this worker cannot read (not JSON, not an object, another
    version's, no ``ok``) is ``internal``, as a refusal code it does not know is: not a refusal of what it sent
    (an upload answered so is sent again, not reported failed: the service may hold the episode or not)."""
    try:
        obj = protocol.decode(data)
        if not isinstance(obj.get("ok"), bool):
            raise protocol.bad_field(f'expected "ok": true or false, found {obj.get("ok")!r:.40}')
    except ProtocolError as exc:
        raise ProtocolError(ErrorCode.INTERNAL, f"the reply could not be read ({exc})") from None
    return protocol.reply_body(obj)


class Worker:
    """One collector: ``run()`` until stopped, ``max_episodes`` reached, or (``once``) one request."""

    def __init__(self, config: WorkerConfig) -> None:
        self.config = config
        self.keys: Keys = config.keys
        self.session: zenoh.Session | None = None
        self._token: Any = None
        self._stop = threading.Event()
        self._abort = threading.Event()
        self._stops = 0  # stop signals taken (the drain signal is not one)
        self._calls = Abandoner()  # the queries a second signal walks away from
        self._rng = random.Random(config.worker_id)  # backoff jitter, reproducible per worker
        self.uploaded = 0
        self.failed = 0
        self.released = 0
        self.dropped = 0
        """Episodes given up while draining because a live service would not store them (exit 1)."""
        self._no_parts = False
        """The service takes no upload in parts (an older version): episodes go whole (``workers.upload``)."""
        self.refused: str | None = None
        """Why the last lease query was refused (not ``no_work``) or its reply could not be read; None once one is
        answered. Such queries back off up to ``max_backoff_s``; ``--once`` exits 1 on one."""
        self._refusals = 0
        self.abandoned: list[str] = []
        """``<request id> (<what it was doing>)`` of an episode a second stop signal dropped unacknowledged (exit 1)."""

    # --- lifecycle -----------------------------------------------------------------------------

    def stop(self) -> None:
        """A stop signal: drain; a second one gives the current request back, whether ``drain`` came first or not."""
        # (On a thread of its own, never inside the signal handler: it may take locks.)
        self._stops += 1
        if self._stops == 1:
            self.drain("(signal again to give it back)")
        else:
            self._abort.set()
            self._calls.abandon()
            log.info("stopping now: giving the current request back")

    def drain(self, why: str = "(asked to drain)") -> None:
        """Finish the current request, then return from ``run``; again: nothing (never gives the request back)."""
        log.info("draining already %s" if self._stop.is_set() else "draining: finishing the current request %s", why)
        self._stop.set()

    def install_signal_handlers(self) -> None:
        """SIGTERM / SIGINT call ``stop``, DRAIN_SIGNAL ``drain`` (main thread only; ``orchestrator.signals``:
        a SIGINT this process was started ignoring stays ignored, so a worker of ``activecollect run`` does not
        stop on a SIGINT its run ignores)."""
        signals.on_stop_signals(self.stop, also={DRAIN_SIGNAL: self.drain})

    def run(self) -> int:
        """Work until stopped; returns the number of episodes uploaded. Raises WorkerError on start."""
        cfg = self.config
        try:
            self.session = transport.open_session(cfg.mode, cfg.listen, cfg.connect, cfg.zenoh_config)
        except transport.TransportError as exc:
            raise WorkerError(str(exc)) from exc
        try:
            self._token = self.session.liveliness().declare_token(self.keys.worker(cfg.worker_id))
            log.info("worker %s up (tasks %s, shapes %s)", cfg.worker_id, list(cfg.tasks) or "any",
                     list(cfg.shapes) or "any")
            self._loop()
        finally:
            if self._token is not None:
                self._token.undeclare()
            self.session.close()
        log.info("worker %s done: %d uploaded, %d failed, %d released, %d given up", cfg.worker_id, self.uploaded,
                 self.failed, self.released, self.dropped)
        return self.uploaded

    def _loop(self) -> None:
        cfg = self.config
        while not self._stop.is_set():
            if cfg.max_episodes is not None and self.uploaded >= cfg.max_episodes:
                return
            grant = self._lease()
            if grant is None:
                if self._stop.is_set():  # drained while waiting for an answer: not "no work"
                    return
                if cfg.once:
                    if self.refused is None:
                        log.info("no work; exiting (--once)")
                    return
                self._stop.wait(self._idle_wait())
                continue
            if self._stop.is_set():  # drained while the lease was asked for: this request is not in hand yet
                log.info("draining: giving back %s, granted after the drain began", grant.request_id)
                self._release(grant)
                return
            # Logged once in hand (past the drain check): a drain signal from here on finishes this request.
            log.info("leased %s token %d (%s, %s, %d steps)", grant.request_id, grant.token, grant.shape,
                     grant.policy, grant.steps)
            self._handle(grant)
            if cfg.once:
                return

    # --- talking to the service ----------------------------------------------------------------

    def _call(self, key: str, payload: bytes, attachment: bytes | None = None,
              timeout: float | None = None, abandon: bool = True) -> dict[str, Any]:
        """One query; the reply body. Raises TransportError (nobody answered; ``Abandoned``: a second stop
        signal came first, unless ``abandon`` is False) or ProtocolError (refused)."""
        def ask() -> bytes:
            return transport.query(self.session, key, payload, attachment, timeout=timeout or self.config.timeout_s)
        return read_reply(self._calls.run(ask, key) if abandon else ask())

    def _retrying(self, what: str, fn: Callable[[], dict[str, Any]], attempts: int | None = None,
                  until_stopped: bool = False, give_up: Callable[[], bool] = lambda: False,
                  transient: tuple[ErrorCode, ...] = (), progress: Callable[[], Any] = lambda: None
                  ) -> dict[str, Any] | None:
        """``fn()`` retried with exponential backoff while nobody answers (or refuses with a ``transient`` code).

        None when out of ``attempts``, when ``give_up()`` says so, when told to give the request back,
        or (``until_stopped``) when told to drain: no try after that, nor a wait for the next one.
        Any other ProtocolError (a refusal) propagates.
        """
        delay, n = 0.1, 0
        while True:
            before = progress()
            try:
                return fn()
            except Abandoned:
                return None
            except (transport.TransportError, ProtocolError) as exc:
                if isinstance(exc, ProtocolError) and exc.code not in transient:
                    raise
                n += 1
                if until_stopped and self._stop.is_set():  # the caller says what it leaves undone
                    return None
                if give_up() or (attempts is not None and n >= attempts):
                    log.warning("%s: giving up after %d attempts: %s", what, n, exc)
                    return None
                if progress() != before:  # (an upload in parts that got on: its next trouble backs off from the start)
                    delay = 0.1
                wait = min(delay * (0.5 + self._rng.random()), self.config.max_backoff_s)
                log.warning("%s: %s; retrying in %.2f s", what, exc, wait)
                if (self._stop if until_stopped else self._abort).wait(wait):  # (a give-back sets both)
                    return None
                delay *= 2

    def _lease(self) -> LeaseGrant | None:
        cfg = self.config
        msg = messages.LeaseRequest(worker_id=cfg.worker_id, tasks=list(cfg.tasks), shapes=list(cfg.shapes),
                                    image_size=cfg.image_size).to_json()  # "I record at the grant's size"
        try:
            body = self._retrying("lease", lambda: self._call(self.keys.lease, msg), until_stopped=True,
                                  transient=(ErrorCode.UNAVAILABLE,))  # e.g. its disk is full: back off
        except ProtocolError as exc:
            if exc.code == ErrorCode.NO_WORK:
                self.refused, self._refusals = None, 0
                return None
            return self._lease_refused(f"the lease query was refused, or its reply could not be read: {exc}")
        if body is None:
            return None
        raw = body.get("grant")
        if not isinstance(raw, dict):  # names no request: there is nothing to report failed
            return self._lease_refused(f"the lease reply is malformed: expected a grant object, found {raw!r:.80}")
        self.refused, self._refusals = None, 0
        try:
            grant = LeaseGrant.from_dict(raw)
        except ProtocolError as exc:  # a request no worker can do: say so, so it ends dead, not looping
            log.warning("lease of %s is malformed: %s", raw.get("request_id"), exc)
            self._fail_raw(str(raw.get("request_id")), raw.get("token"), f"malformed lease: {exc}")
            return None
        return grant

    def _idle_wait(self) -> float:
        """Seconds before the next lease query: the idle poll, doubled with each refusal in a row up to the backoff's
        most (a refusal that will not pass, another release's service, must not be asked twice a second)."""
        cfg = self.config
        if self.refused is None:
            return cfg.idle_poll_s
        return min(cfg.idle_poll_s * 2 ** min(self._refusals, 16), max(cfg.max_backoff_s, cfg.idle_poll_s))

    def _lease_refused(self, why: str) -> None:
        self.refused, self._refusals = why, self._refusals + 1
        log.warning("%s (a service of another release than this worker's, or one in trouble: see its log; %d in "
                    "a row; asking again after a backoff)", why, self._refusals)

    def _fail(self, grant: LeaseGrant, error: str) -> None:
        self._fail_raw(grant.request_id, grant.token, error)

    def _fail_raw(self, request_id: str, token: Any, error: str) -> None:
        """Report a failure: ``report_attempts`` tries; once a stop was asked, one short one (``STOPPING_TIMEOUT_S``)
        and no more (a stop asked while it retries ends the retries): a service that is gone must not hold a
        stopping worker for minutes."""
        timeout = min(STOPPING_TIMEOUT_S, self.config.timeout_s) if self._stop.is_set() else self.config.timeout_s
        try:
            msg = messages.FailRequest(request_id=request_id, token=token, worker_id=self.config.worker_id,
                                       error=error[:protocol.MAX_ERROR_CHARS]).to_json()
            body = self._retrying("fail", lambda: self._call(self.keys.fail, msg, timeout=timeout),
                                  self.config.report_attempts, until_stopped=True)
        except ProtocolError as exc:
            log.warning("fail %s refused: %s", request_id, exc)
            return
        self.failed += 1
        if body is not None:
            log.info("reported failure of %s: now %s after %s attempt(s)", request_id,
                     body.get("status"), body.get("attempts"))
        elif self._stop.is_set():
            log.warning("stopping: could not report the failure of %s (%.200s): the service takes the request back "
                        "when its lease or this worker's liveliness ends (counting the attempt)", request_id, error)

    def _release(self, grant: LeaseGrant) -> None:
        """Give a lease back unharmed (a second stop signal): one short try, the service may be going too."""
        msg = messages.ReleaseRequest(request_id=grant.request_id, token=grant.token,
                                      worker_id=self.config.worker_id).to_json()
        timeout = min(STOPPING_TIMEOUT_S, self.config.timeout_s)
        try:
            body = self._retrying("release", lambda: self._call(self.keys.release, msg, timeout=timeout,
                                                                abandon=False), 1)
        except ProtocolError as exc:  # stale: the request is not ours any more anyway
            log.warning("release of %s refused: %s", grant.request_id, exc)
            return
        if body is None:
            log.warning("release of %s not answered; the service ends the lease when this worker's "
                        "liveliness token goes (counting an attempt)", grant.request_id)
            return
        self.released += 1
        log.info("released %s: %s again, %s attempt(s)", grant.request_id, body.get("status"), body.get("attempts"))

    # --- one request -----------------------------------------------------------------------------

    def _handle(self, grant: LeaseGrant) -> None:
        renewer = Renewer(lambda k, m, t: self._call(k, m, timeout=min(t, self.config.timeout_s), abandon=False),
                          self.keys.renew, grant, self.config.worker_id)
        try:
            started = time.monotonic()
            try:
                data, frames = self._record(grant)
            except CollectionStopped as exc:
                self._abandon(grant, f"collecting: {exc}")
                return
            except Exception as exc:  # noqa: BLE001 -- any collection failure is reported, not hidden
                log.warning("collection of %s failed: %s: %s", grant.request_id, type(exc).__name__, exc)
                self._fail(grant, f"collection failed: {type(exc).__name__}: {exc}")
                return
            if not self._pace(started, frames, renewer):
                self._abandon(grant, "collected, not uploaded")
                return
            if renewer.lost is not None:
                log.warning("dropping the episode of %s: the lease is no longer ours", grant.request_id)
                return
            self._upload(grant, data, renewer)
        finally:  # given back: not after a renewal in flight; stopping: not long after one to a service gone
            renewer.stop(wait=not self._abort.is_set(), timeout=STOPPING_TIMEOUT_S if self._stop.is_set() else None)

    def _abandon(self, grant: LeaseGrant, doing: str) -> None:
        """A second stop signal: the episode of ``grant`` (never acknowledged) is dropped, the request given back."""
        self.abandoned.append(f"{grant.request_id} ({doing})")
        self._release(grant)

    def _record(self, grant: LeaseGrant) -> tuple[bytes, int]:
        """The episode's MCAP bytes and its number of frames (the decoded episode is not kept while it uploads).
        Raises what collecting raises, and ValueError for bytes no upload may carry."""
        episode = self._collect(grant)
        data = encode_episode(episode)
        if len(data) > protocol.MAX_UPLOAD_BYTES:  # every worker would record the same: a failure, not a retry
            raise ValueError(f"episode: expected at most {protocol.MAX_UPLOAD_BYTES} bytes of MCAP (the most an "
                             f"upload carries), found {len(data)}")
        return data, len(episode)

    def _collect(self, grant: LeaseGrant):
        prefix = np.asarray(grant.action_prefix, np.float32).reshape(-1, 2) if grant.action_prefix else None
        return collect_episode(start_state=grant.start_state, policy=grant.policy,
                               policy_params=grant.policy_params, seed=grant.seed, steps=grant.steps,
                               image_size=grant.image_size or self.config.image_size, action_prefix=prefix,
                               request_id=grant.request_id, worker_id=self.config.worker_id,
                               model_version=grant.model_version, stop=self._abort.is_set)

    def _pace(self, started: float, frames: int, renewer: Renewer | None = None) -> bool:
        """Wait out the episode's real duration when pacing, or until ``renewer`` finds the lease lost (the episode
        is dropped then: no use waiting); False if told to give the request back."""
        end = started + self.config.realtime * frames / CONTROL_HZ
        while (remaining := end - time.monotonic()) > 0 and (renewer is None or renewer.lost is None):
            if self._abort.wait(min(remaining, PACE_CHECK_S)):
                return False
        return not self._abort.is_set()

    def _upload(self, grant: LeaseGrant, data: bytes, renewer: Renewer) -> None:
        """Upload until the service acknowledges it, refuses the data, or the lease is lost.

        No reply, ``internal`` and ``unavailable`` (a full disk, a busy database, a service going
        down) are retried with the same bytes: a collected episode is not dropped while its lease
        is ours. While draining, for one more lease term at most (``Renewer.drain_left``; each part the
        service takes starts it again), then ``_give_up``. A second stop signal gives the request back instead.
        """
        upload = EpisodeUpload(data, grant.request_id, grant.token, self.config.worker_id,
                               None if self._no_parts else self.config.part_bytes)
        last: list[Exception] = []  # the last try's failure
        seen = [0]  # the most bytes the service said it held: a new high is progress (once a part at most)

        def send(payload: bytes, attachment: bytes) -> dict[str, Any]:
            timeout = self.config.timeout_s
            if upload.held > seen[0]:  # the last part was taken: a draining worker's term goes on from here
                seen[0] = upload.held
                renewer.drain_progress()
            if self._stop.is_set():  # draining: no wait past the end of the lease or of the drain's term
                timeout = min(timeout, max(renewer.drain_left(), MIN_DRAIN_ATTEMPT_S))
            return self._call(self.keys.upload, payload, attachment, timeout=timeout)

        def attempt() -> dict[str, Any]:  # the whole, or the parts from the last the service holds
            try:
                return upload.send_with(send)
            except (transport.TransportError, ProtocolError) as exc:
                last[:] = [exc]
                raise

        def ran_out() -> bool:
            return self._stop.is_set() and renewer.drain_left() <= 0

        asked_again: list[bool] = []

        def give_up() -> bool:
            # A renewal refused once the upload went out may have met the request this very upload completed (its
            # reply lost or late): one more try is answered 'duplicate' then, 'stale_token' if the lease is gone.
            if renewer.lost is not None and not asked_again:
                asked_again.append(True)
                return ran_out()
            return renewer.lost is not None or ran_out()

        renewer.uploading = True
        try:
            body = self._retrying("upload", attempt, give_up=give_up, progress=lambda: upload.held,
                                  transient=(ErrorCode.INTERNAL, ErrorCode.UNAVAILABLE))
        except ProtocolError as exc:
            if exc.code in (ErrorCode.STALE_TOKEN, ErrorCode.UNKNOWN_REQUEST):
                log.warning("upload of %s refused (%s): the lease is no longer ours", grant.request_id, exc)
            else:
                log.warning("upload of %s refused: %s", grant.request_id, exc)
                self._fail(grant, f"upload refused: {exc}")
            return
        finally:
            self._no_parts = self._no_parts or upload.no_parts_here
        if body is not None:
            self.uploaded += 1
            log.info("uploaded %s: episode %s%s", grant.request_id, body.get("episode_id"),
                     " (duplicate)" if body.get("duplicate") else "")
        elif self._abort.is_set():
            self._abandon(grant, "uploading, not acknowledged")
        elif renewer.lost is not None:
            log.warning("dropping the episode of %s: the lease is no longer ours (%s)", grant.request_id, renewer.lost)
        else:
            self._give_up(grant, len(data), last[0], renewer)

    def _give_up(self, grant: LeaseGrant, size: int, last: Exception, renewer: Renewer) -> None:
        """Draining, and the upload was not acknowledged in time: the episode (held in memory only) is dropped.
        A service that is there (it answered, or still renews the lease) but would not store it is told,
        by giving the request back, and the worker will exit 1: collected work was lost."""
        if isinstance(last, ProtocolError) or renewer.remaining() > 0:
            self.dropped += 1
            log.error("giving up the episode of %s (%d bytes, never stored): draining, and the service did not "
                      "store it within a lease term (last: %s); giving the request back", grant.request_id, size, last)
            self._release(grant)
        else:  # nobody answers (the service is gone): it queues the request again when its lease expires
            log.warning("dropping the episode of %s: draining, and the service did not acknowledge it before the "
                        "lease ran out", grant.request_id)


if __name__ == "__main__":  # ``python -m workers.agent``: the command line lives in workers.cli
    from workers.cli import main
    sys.exit(main())
