"""The wire messages: one dataclass per kind of message, each checking itself.

Built on ``orchestrator.protocol`` (limits, error codes, field checks, JSON
encoding) and importing nothing else of ours, so it is a leaf of the wire
contract too: workers on any host may depend on it.

Per key, the message it takes and the reply (ok_reply / error_reply / duplicate_reply):
  orch/lease   LeaseRequest            -> ok {"grant": LeaseGrant.to_dict()} | error no_work
  orch/renew   RenewRequest            -> ok {"expires_at": t} | error stale_token, unknown_request
  orch/upload  UploadHeader attachment -> ok {"request_id", "episode_id"} | duplicate_reply(same)
               + raw MCAP payload         | error stale_token, hash_mismatch, corrupt_episode, too_large
               UploadPart attachment   -> ok {"request_id", "received": n} until the last part, answered as above
               + bytes [offset, ...)
  orch/fail    FailRequest             -> ok {"status": "queued" | "dead", "attempts": n} | error stale_token
  orch/release ReleaseRequest          -> ok {"status": "queued", "attempts": n} | error stale_token
  admin/<op>   AdminRequest (or empty) -> ok with the op's body (orchestrator.admin) | error
  events/**    Event (publications)
Any key: bad_json, bad_version, bad_field, too_large for a malformed message; internal for a bug;
unavailable when storage cannot do it now (a full disk, a busy or failing SQLite file; every orch/
and admin/ operation that touches storage may answer it): the worker keeps its episode and retries.
"""

from __future__ import annotations

import dataclasses
import hashlib
import re
from dataclasses import dataclass, field
from typing import Any

from orchestrator.protocol import (ADMIN_OPS, MAX_ATTEMPTS, MAX_EPISODE_STEPS, MAX_ERROR_CHARS, MAX_FRAME_SIZE,
                                   MAX_UPLOAD_BYTES, MIN_EPISODE_STEPS, MIN_FRAME_SIZE, POLICIES, PROTOCOL_VERSION,
                                   MAX_PRIORITY, SHAPES, TASKS,
                                   ErrorCode, EventKind, ProtocolError, bad_field, check_float, check_id, check_int,
                                   check_obj, check_str, check_str_list, decode, encode,
                                   validate_action_prefix, validate_start_state)

_SHA256_RE = re.compile(r"^[0-9a-f]{64}$")


class Message:
    """Base of the wire messages: dataclasses that check themselves in ``__post_init__``."""

    def __post_init__(self) -> None:
        self.validate()

    def validate(self) -> None:  # pragma: no cover - every message overrides it
        """Check (and normalise) every field; raise ProtocolError."""

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    def to_json(self) -> bytes:
        # Fields are JSON values already (validated), so no deep copy on the way to the encoder.
        ordered, _, _ = _field_names(type(self))
        return encode({"v": PROTOCOL_VERSION, **{name: getattr(self, name) for name in ordered}})

    @classmethod
    def from_dict(cls, obj: Any) -> Any:
        """Build and validate from a decoded object (no ``"v"``); unknown or missing fields are refused."""
        if not isinstance(obj, dict):
            raise bad_field(f"{cls.__name__}: expected a JSON object, found {type(obj).__name__}")
        _, names, required = _field_names(cls)
        if not names.issuperset(obj):
            unknown = sorted(set(obj) - names, key=str)
            raise bad_field(f"{cls.__name__}: unknown field(s) {', '.join(map(repr, unknown))[:200]}")
        if not required.issubset(obj):
            missing = [f.name for f in dataclasses.fields(cls) if f.name in required and f.name not in obj]
            raise bad_field(f"{cls.__name__}: missing field(s) {', '.join(missing)}")
        return cls(**obj)

    @classmethod
    def from_json(cls, data: bytes | bytearray | memoryview | str | None) -> Any:
        return cls.from_dict(decode(data))


_FIELDS: dict[type, tuple[tuple[str, ...], frozenset[str], frozenset[str]]] = {}


def _field_names(cls: type) -> tuple[tuple[str, ...], frozenset[str], frozenset[str]]:
    """(field names in order, the same as a set, required field names) of a message class, once per class."""
    cached = _FIELDS.get(cls)
    if cached is None:
        fields = dataclasses.fields(cls)
        names = tuple(f.name for f in fields)
        cached = _FIELDS[cls] = (names, frozenset(names), frozenset(
            f.name for f in fields if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING))
    return cached


# --- worker messages ----------------------------------------------------------


@dataclass
class LeaseRequest(Message):
    """Worker -> ``NS/orch/lease``: give me a request I can do. Empty lists mean "any"."""

    worker_id: str
    tasks: list[str] = field(default_factory=list)
    shapes: list[str] = field(default_factory=list)
    image_size: int = 0
    """The worker's own frame size. A worker that sends it records at the grant's ``image_size``, and only
    to such a worker does the service send that field (older workers refuse unknown fields); 0: not sent."""

    def validate(self) -> None:
        check_id("worker_id", self.worker_id)
        self.tasks = check_str_list("tasks", self.tasks, TASKS)
        self.shapes = check_str_list("shapes", self.shapes, SHAPES)
        self.image_size = _check_frame_size(self.image_size)


def request_seed(request_id: str, token: int) -> int:
    """The collection seed of one lease: stable per (request, attempt), 31 bits."""
    digest = hashlib.sha256(f"{request_id}:{token}".encode()).digest()
    return int.from_bytes(digest[:4], "big") & 0x7FFFFFFF


@dataclass
class LeaseGrant(Message):
    """Orchestrator -> worker (the ``grant`` of a lease reply): what to collect and the lease."""

    request_id: str
    task: str
    shape: str
    start_state: dict[str, Any]
    policy: str
    policy_params: dict[str, Any]
    action_prefix: list[list[float]]
    steps: int
    model_version: str
    """Model version that asked for this request ("" for uniform / manual requests)."""
    token: int
    """Fencing token: renew / upload / fail must carry it."""
    expires_at: float
    """Lease expiry, Unix seconds (orchestrator clock)."""
    lease_s: float
    """Lease length; renew well before it runs out (e.g. every lease_s / 3)."""
    seed: int = 0
    """Seed of the collection policy's generator (see :func:`request_seed`)."""
    image_size: int = 0
    """Frame size the service's catalog holds, which the episode must have; 0 while it holds none
    (the worker's own size then). Sent only to workers whose lease request gave theirs."""

    def validate(self) -> None:
        check_id("request_id", self.request_id)
        _check_collection(self)
        self.model_version = check_str("model_version", self.model_version, allow_empty=True)
        self.token = check_int("token", self.token, 1, 2**62)
        self.expires_at = check_float("expires_at", self.expires_at, 0.0)
        self.lease_s = check_float("lease_s", self.lease_s, 0.001, 86400.0)
        self.seed = check_int("seed", self.seed, 0, 2**32 - 1)
        self.image_size = _check_frame_size(self.image_size)


def _check_frame_size(value: Any) -> int:
    """An ``image_size`` field: 0 (none) or a frame size episodes may have."""
    value = check_int("image_size", value, 0, MAX_FRAME_SIZE)
    if 0 < value < MIN_FRAME_SIZE:
        raise bad_field(f"image_size: expected 0 or {MIN_FRAME_SIZE}..{MAX_FRAME_SIZE}, found {value}")
    return value


def _check_collection(msg: Any) -> None:
    """Shared checks of what a request asks for (LeaseGrant, RequestSpec)."""
    msg.task = check_str("task", msg.task, choices=TASKS)
    msg.shape = check_str("shape", msg.shape, choices=SHAPES)
    msg.start_state = validate_start_state(msg.start_state)
    if msg.start_state["shape"] != msg.shape:
        raise bad_field(f"start_state.shape: expected {msg.shape!r} (the request's shape), "
                        f"found {msg.start_state['shape']!r}")
    msg.policy = check_str("policy", msg.policy, choices=POLICIES)
    msg.policy_params = check_obj("policy_params", msg.policy_params)
    msg.action_prefix = validate_action_prefix(msg.action_prefix)
    msg.steps = check_int("steps", msg.steps, MIN_EPISODE_STEPS, MAX_EPISODE_STEPS)


@dataclass
class LeaseRef(Message):
    """The lease a worker's message is about: the request, the fencing token, the worker holding it."""

    request_id: str
    token: int
    worker_id: str

    def validate(self) -> None:
        check_id("request_id", self.request_id)
        self.token = check_int("token", self.token, 1, 2**62)
        check_id("worker_id", self.worker_id)


@dataclass
class RenewRequest(LeaseRef):
    """Worker -> ``NS/orch/renew``: extend my lease (refused with stale_token if it is not mine any more)."""


@dataclass
class UploadHeader(LeaseRef):
    """Worker -> ``NS/orch/upload`` as the query attachment; the payload is the raw MCAP bytes."""

    sha256: str
    """Lower-case hex sha256 of the payload."""
    size: int
    """Payload length in bytes."""

    def validate(self) -> None:
        super().validate()
        if not isinstance(self.sha256, str) or not _SHA256_RE.fullmatch(self.sha256):
            raise bad_field(f"sha256: expected 64 lower-case hex digits, found {self.sha256!r:.80}")
        if isinstance(self.size, int) and not isinstance(self.size, bool) and self.size > MAX_UPLOAD_BYTES:
            raise ProtocolError(ErrorCode.TOO_LARGE,
                                f"size: expected at most {MAX_UPLOAD_BYTES} bytes, found {self.size}")
        self.size = check_int("size", self.size, 1, MAX_UPLOAD_BYTES)

    @classmethod
    def for_payload(cls, payload: bytes, *, request_id: str, token: int, worker_id: str) -> UploadHeader:
        """The header of an upload of ``payload`` (computes size and sha256)."""
        return cls(request_id=request_id, token=token, worker_id=worker_id,
                   sha256=hashlib.sha256(payload).hexdigest(), size=len(payload))

    def check_payload(self, payload: bytes | bytearray | memoryview | None) -> bytes:
        """The payload as bytes if it matches this header; ProtocolError too_large / bad_field / hash_mismatch."""
        if payload is None:
            raise bad_field("payload: expected the episode's MCAP bytes, found none")
        if len(payload) > MAX_UPLOAD_BYTES:
            raise ProtocolError(ErrorCode.TOO_LARGE,
                                f"payload: expected at most {MAX_UPLOAD_BYTES} bytes, found {len(payload)}")
        data = bytes(payload)
        if len(data) != self.size:
            raise bad_field(f"payload: expected {self.size} bytes (header size), found {len(data)}")
        digest = hashlib.sha256(data).hexdigest()
        if digest != self.sha256:
            raise ProtocolError(ErrorCode.HASH_MISMATCH, f"payload: expected sha256 {self.sha256}, found {digest}")
        return data


@dataclass
class UploadPart(UploadHeader):
    """Worker -> ``NS/orch/upload``: one part of an upload sent in parts (``orchestrator.upload_parts``): the
    whole upload's header (``sha256`` and ``size`` are the whole episode's) and where in it the payload goes.
    Answered ok ``{"request_id", "received": n}`` (the bytes held from the start, from which to send on) until
    the part that completes the bytes, which is answered as a whole upload is."""

    offset: int

    def validate(self) -> None:
        super().validate()
        self.offset = check_int("offset", self.offset, 0, self.size - 1)

    def whole(self) -> UploadHeader:
        """The header of the upload this part is of."""
        return UploadHeader(request_id=self.request_id, token=self.token, worker_id=self.worker_id,
                            sha256=self.sha256, size=self.size)

    @classmethod
    def of(cls, header: UploadHeader, offset: int) -> UploadPart:
        return cls(request_id=header.request_id, token=header.token, worker_id=header.worker_id,
                   sha256=header.sha256, size=header.size, offset=offset)


def upload_header(attachment: bytes | bytearray | memoryview | None) -> UploadHeader:
    """The header of an ``NS/orch/upload`` query: an ``UploadPart`` when it gives an offset."""
    obj = decode(attachment)
    return (UploadPart if isinstance(obj, dict) and "offset" in obj else UploadHeader).from_dict(obj)


@dataclass
class FailRequest(LeaseRef):
    """Worker -> ``NS/orch/fail``: give the lease back with an error (counts an attempt)."""

    error: str

    def validate(self) -> None:
        super().validate()
        self.error = check_str("error", self.error, max_len=MAX_ERROR_CHARS)


@dataclass
class ReleaseRequest(LeaseRef):
    """Worker -> ``NS/orch/release``: give the lease back unharmed (a draining worker; no attempt counted)."""


# --- requests, admin, events --------------------------------------------------


@dataclass
class RequestSpec(Message):
    """A collection request as a planner or an operator (``queue.add``) asks for it; validated."""

    task: str
    shape: str
    start_state: dict[str, Any]
    policy: str = "push"
    policy_params: dict[str, Any] = field(default_factory=dict)
    action_prefix: list[list[float]] = field(default_factory=list)
    steps: int = 50
    priority: float = 0.0
    reason: dict[str, Any] = field(default_factory=dict)
    """Why it exists: model_version, score, source_episode, step, planner."""
    max_attempts: int = 3
    idempotency_key: str | None = None

    def validate(self) -> None:
        _check_collection(self)
        self.priority = check_float("priority", self.priority, -MAX_PRIORITY, MAX_PRIORITY)
        self.reason = check_obj("reason", self.reason)
        if self.reason.get("model_version") is not None:  # it goes into every grant, which workers check
            check_str("reason.model_version", self.reason["model_version"], allow_empty=True)
        self.max_attempts = check_int("max_attempts", self.max_attempts, 1, MAX_ATTEMPTS)
        if self.idempotency_key is not None:
            self.idempotency_key = check_str("idempotency_key", self.idempotency_key, max_len=256)


@dataclass
class AdminRequest(Message):
    """Operator -> ``NS/admin/<op>``: one admin operation with its arguments."""

    op: str
    args: dict[str, Any] = field(default_factory=dict)

    def validate(self) -> None:
        if not isinstance(self.op, str) or self.op not in ADMIN_OPS:
            raise ProtocolError(ErrorCode.UNKNOWN_OP,
                                f"op: expected one of {', '.join(ADMIN_OPS)}, found {self.op!r:.80}")
        self.args = check_obj("args", self.args)


@dataclass
class Event(Message):
    """One published event: its kind, when (Unix seconds) and a small JSON object."""

    kind: str
    at: float
    data: dict[str, Any] = field(default_factory=dict)

    def validate(self) -> None:
        try:
            self.kind = EventKind(self.kind).value
        except ValueError:
            raise bad_field(f"kind: expected one of {', '.join(k.value for k in EventKind)}, "
                            f"found {self.kind!r:.80}") from None
        self.at = check_float("at", self.at, 0.0)
        self.data = check_obj("data", self.data)
