"""The wire contract between orchestrator, workers and operators.

A leaf module: it imports nothing else of ours, so workers on any host can
depend on it without pulling in the service.

Section 1 (this header) is the task space: what a collection request may ask
for. Both the uniform planner (which samples it) and the simulator (which
builds worlds from it) read these constants, so they cannot drift apart.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import re
from dataclasses import dataclass, field
from enum import Enum
from typing import Any

#: Side of the square table in world units; y points up, origin bottom-left.
WORLD_SIZE = 512.0
#: Thickness of the walls along the table's border (inside WORLD_SIZE).
WALL = 8.0
#: Task families a worker may declare. One for now.
TASKS: tuple[str, ...] = ("push",)
#: Object shapes of the push task.
SHAPES: tuple[str, ...] = ("T", "box", "L", "disk")
#: Where start states are drawn from: object centre and agent position (world units).
OBJECT_RANGE = (128.0, 384.0)
AGENT_RANGE = (40.0, 472.0)
#: Physics parameters, each (low, high, default). Out-of-range values are refused.
PHYSICS_RANGES: dict[str, tuple[float, float, float]] = {
    "mass": (0.2, 5.0, 1.0),
    "friction": (0.05, 1.5, 0.6),
    "ground_friction": (0.05, 3.0, 1.0),
}
#: Collection policies a request may name.
POLICIES: tuple[str, ...] = ("random_waypoints", "push")
#: Hard caps used by validation.
MAX_EPISODE_STEPS = 1000
MAX_PREFIX_STEPS = 1000

# ---------------------------------------------------------------------------
# Section 2: the messages. Everything below validates what crosses the wire.
#
# Every reply is {"v": 1, "ok": true, ...body} or {"v": 1, "ok": false, "error": code,
# "message": why} (ok_reply / error_reply / parse_reply). Per key:
#   orch/lease   LeaseRequest            -> ok {"grant": LeaseGrant.to_dict()} | error no_work
#   orch/renew   RenewRequest            -> ok {"expires_at": t} | error stale_token, unknown_request
#   orch/upload  UploadHeader attachment -> ok {"request_id", "episode_id"} | duplicate_reply(same)
#                + raw MCAP payload         | error stale_token, hash_mismatch, corrupt_episode, too_large
#   orch/fail    FailRequest             -> ok {"status": "queued" | "dead", "attempts": n} | error stale_token
#   orch/release ReleaseRequest          -> ok {"status": "queued", "attempts": n} | error stale_token
#   admin/<op>   AdminRequest (or empty) -> ok with the op's body (orchestrator.admin) | error
# Any key: bad_json, bad_version, bad_field, too_large for a malformed message; internal for a bug.
# ---------------------------------------------------------------------------

#: Version every JSON message carries as ``"v"``; a message with another version is refused.
PROTOCOL_VERSION = 1
#: Largest JSON message (query payload, attachment, reply) accepted, in bytes.
MAX_MESSAGE_BYTES = 256 * 1024
#: Largest episode upload (raw MCAP bytes), in bytes.
MAX_UPLOAD_BYTES = 64 * 1024 * 1024
#: Largest encoded ``policy_params`` / ``reason`` / admin ``args`` / event ``data`` object, in bytes.
MAX_OBJECT_BYTES = 16 * 1024
#: Largest error text a worker may report.
MAX_ERROR_CHARS = 4096
#: Largest |velocity| in a start state (world units/s) and |angular velocity| (rad/s).
MAX_SPEED = 10 * WORLD_SIZE
MAX_OMEGA = 100.0
#: Most tasks / shapes a worker may declare.
MAX_CAPABILITIES = 32
#: Most attempts a request may be given.
MAX_ATTEMPTS = 100

_ID_RE = re.compile(r"^[A-Za-z0-9_.\-]{1,128}$")
_NAMESPACE_RE = re.compile(r"^[A-Za-z0-9_\-]+(/[A-Za-z0-9_\-]+)*$")
_SHA256_RE = re.compile(r"^[0-9a-f]{64}$")
_OP_RE = re.compile(r"^[a-z]+(\.[a-z_]+)*$")


class ErrorCode(str, Enum):
    """Why a message was refused; sent as ``"error"`` in an error reply."""

    BAD_JSON = "bad_json"
    BAD_VERSION = "bad_version"
    BAD_FIELD = "bad_field"
    TOO_LARGE = "too_large"
    STALE_TOKEN = "stale_token"
    UNKNOWN_REQUEST = "unknown_request"
    ILLEGAL_TRANSITION = "illegal_transition"
    HASH_MISMATCH = "hash_mismatch"
    CORRUPT_EPISODE = "corrupt_episode"
    NO_WORK = "no_work"
    UNKNOWN_OP = "unknown_op"
    UNAVAILABLE = "unavailable"
    INTERNAL = "internal"


class ProtocolError(Exception):
    """Root of the orchestrator's wire-layer errors: a refused message, with a code and a reason."""

    def __init__(self, code: ErrorCode | str, message: str) -> None:
        self.code = ErrorCode(code)
        self.message = message
        super().__init__(f"{self.code.value}: {message}")

    def reply(self) -> bytes:
        """This error as an error reply (JSON bytes)."""
        return error_reply(self.code, self.message)


def _bad(message: str) -> ProtocolError:
    return ProtocolError(ErrorCode.BAD_FIELD, message)


# --- keys -------------------------------------------------------------------


def check_id(name: str, value: Any) -> str:
    """A request / worker / episode id: 1-128 chars of ``[A-Za-z0-9_.-]`` (safe as one key chunk)."""
    if not isinstance(value, str) or not _ID_RE.match(value):
        raise _bad(f"{name}: expected 1-128 characters of [A-Za-z0-9_.-], found {value!r:.80}")
    return value


@dataclass(frozen=True)
class Keys:
    """The Zenoh key space of one deployment, under ``namespace``."""

    namespace: str = "activecollect"
    """Prefix of every key: chunks of ``[A-Za-z0-9_-]`` joined by ``/``, no wildcards."""

    def __post_init__(self) -> None:
        if not isinstance(self.namespace, str) or not _NAMESPACE_RE.match(self.namespace):
            raise _bad(f"namespace: expected chunks of [A-Za-z0-9_-] joined by '/', "
                       f"found {self.namespace!r}")

    @property
    def lease(self) -> str:
        return f"{self.namespace}/orch/lease"

    @property
    def renew(self) -> str:
        return f"{self.namespace}/orch/renew"

    @property
    def upload(self) -> str:
        return f"{self.namespace}/orch/upload"

    @property
    def fail(self) -> str:
        return f"{self.namespace}/orch/fail"

    @property
    def release(self) -> str:
        return f"{self.namespace}/orch/release"

    def admin(self, op: str) -> str:
        """Key of one admin op: ``queue.ls`` -> ``NS/admin/queue/ls``."""
        if op not in ADMIN_OPS:
            raise ProtocolError(ErrorCode.UNKNOWN_OP, f"expected one of {', '.join(ADMIN_OPS)}, found {op!r}")
        return f"{self.namespace}/admin/{op.replace('.', '/')}"

    @property
    def admin_all(self) -> str:
        return f"{self.namespace}/admin/**"

    def admin_op(self, key: str) -> str:
        """The op a concrete admin key names (inverse of :meth:`admin`); ProtocolError if none."""
        prefix = f"{self.namespace}/admin/"
        op = key[len(prefix):].replace("/", ".") if key.startswith(prefix) else ""
        if op not in ADMIN_OPS:
            raise ProtocolError(ErrorCode.UNKNOWN_OP, f"expected an admin key for one of "
                                f"{', '.join(ADMIN_OPS)}, found {key!r}")
        return op

    def worker(self, worker_id: str) -> str:
        """Liveliness key of one worker."""
        return f"{self.namespace}/workers/{check_id('worker_id', worker_id)}"

    @property
    def workers_prefix(self) -> str:
        """``NS/workers`` (subscribe to ``workers_all``)."""
        return f"{self.namespace}/workers"

    @property
    def workers_all(self) -> str:
        return f"{self.namespace}/workers/*"

    def worker_id(self, key: str) -> str:
        """The worker id in a liveliness key (inverse of :meth:`worker`)."""
        prefix = self.workers_prefix + "/"
        if not key.startswith(prefix):
            raise _bad(f"expected a key under {prefix}, found {key!r}")
        return check_id("worker_id", key[len(prefix):])

    def events(self, kind: EventKind | str) -> str:
        """Key events of ``kind`` are published on: ``request.done`` -> ``NS/events/request/done``."""
        return f"{self.namespace}/events/{_EVENT_PATHS[EventKind(kind)]}"

    @property
    def events_all(self) -> str:
        return f"{self.namespace}/events/**"

    def event_kind(self, key: str) -> EventKind:
        """The kind an event key names (inverse of :meth:`events`)."""
        prefix = f"{self.namespace}/events/"
        kind = key[len(prefix):].replace("/", ".") if key.startswith(prefix) else ""
        if kind not in {k.value for k in EventKind}:
            raise _bad(f"expected an event key under {prefix}, found {key!r}")
        return EventKind(kind)


# --- field checks -----------------------------------------------------------


def _str(name: str, value: Any, *, max_len: int = 128, choices: tuple[str, ...] | None = None,
         allow_empty: bool = False) -> str:
    if not isinstance(value, str):
        raise _bad(f"{name}: expected a string, found {type(value).__name__}")
    if len(value) > max_len or (not value and not allow_empty):
        raise _bad(f"{name}: expected 1-{max_len} characters, found {len(value)}")
    if choices is not None and value not in choices:
        raise _bad(f"{name}: expected one of {', '.join(choices)}, found {value!r:.80}")
    return value


def _int(name: str, value: Any, lo: int, hi: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        raise _bad(f"{name}: expected an integer, found {type(value).__name__}")
    if not lo <= value <= hi:
        raise _bad(f"{name}: expected an integer in [{lo}, {hi}], found {value}")
    return value


def _float(name: str, value: Any, lo: float = -math.inf, hi: float = math.inf) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise _bad(f"{name}: expected a number, found {type(value).__name__}")
    value = float(value)
    if not math.isfinite(value) or not lo <= value <= hi:
        raise _bad(f"{name}: expected a finite number in [{lo:g}, {hi:g}], found {value!r}")
    return value


def _vec(name: str, value: Any, bounds: list[tuple[float, float]]) -> list[float]:
    if not isinstance(value, (list, tuple)) or len(value) != len(bounds):
        raise _bad(f"{name}: expected a list of {len(bounds)} numbers, found {value!r:.80}")
    return [_float(f"{name}[{i}]", v, lo, hi) for i, (v, (lo, hi)) in enumerate(zip(value, bounds))]


def _obj(name: str, value: Any, max_bytes: int = MAX_OBJECT_BYTES) -> dict[str, Any]:
    if not isinstance(value, dict) or not all(isinstance(k, str) for k in value):
        raise _bad(f"{name}: expected a JSON object with string keys, found {type(value).__name__}")
    try:
        size = len(json.dumps(value, allow_nan=False, separators=(",", ":")))
    except (TypeError, ValueError) as exc:
        raise _bad(f"{name}: expected JSON-encodable finite values ({exc})") from None
    if size > max_bytes:
        raise ProtocolError(ErrorCode.TOO_LARGE, f"{name}: expected at most {max_bytes} bytes, found {size}")
    return dict(value)


def _str_list(name: str, value: Any, choices: tuple[str, ...]) -> list[str]:
    if not isinstance(value, (list, tuple)) or len(value) > MAX_CAPABILITIES:
        raise _bad(f"{name}: expected a list of at most {MAX_CAPABILITIES} strings, found {value!r:.80}")
    return [_str(f"{name}[{i}]", v, choices=choices) for i, v in enumerate(value)]


_POS = (0.0, WORLD_SIZE)
_VEL = (-MAX_SPEED, MAX_SPEED)
_ANGLE = (-1e6, 1e6)
_START_KEYS = {"shape", "agent", "agent_vel", "object", "object_vel", "physics"}


def validate_physics(value: Any, name: str = "physics") -> dict[str, float]:
    """Physics parameters: a subset of PHYSICS_RANGES' keys, each within its (low, high)."""
    value = _obj(name, value)
    unknown = sorted(set(value) - set(PHYSICS_RANGES))
    if unknown:
        raise _bad(f"{name}: expected keys among {', '.join(PHYSICS_RANGES)}, found {', '.join(unknown)}")
    return {k: _float(f"{name}.{k}", v, *PHYSICS_RANGES[k][:2]) for k, v in value.items()}


def validate_start_state(value: Any, name: str = "start_state") -> dict[str, Any]:
    """A simulator state in ``SimState.to_dict`` form, inside the task space; returns a clean copy.

    Required: shape (in SHAPES), agent [x, y], object [x, y, theta] (positions within the world).
    Optional: agent_vel [vx, vy], object_vel [vx, vy, omega], physics. Raises ProtocolError(bad_field).
    """
    value = _obj(name, value)
    unknown = sorted(set(value) - _START_KEYS)
    missing = sorted({"shape", "agent", "object"} - set(value))
    if unknown or missing:
        raise _bad(f"{name}: expected keys {', '.join(sorted(_START_KEYS))} (shape, agent, object "
                   f"required); unknown {unknown}, missing {missing}")
    out: dict[str, Any] = {"shape": _str(f"{name}.shape", value["shape"], choices=SHAPES),
                           "agent": _vec(f"{name}.agent", value["agent"], [_POS, _POS]),
                           "object": _vec(f"{name}.object", value["object"], [_POS, _POS, _ANGLE])}
    if "agent_vel" in value:
        out["agent_vel"] = _vec(f"{name}.agent_vel", value["agent_vel"], [_VEL, _VEL])
    if "object_vel" in value:
        out["object_vel"] = _vec(f"{name}.object_vel", value["object_vel"],
                                 [_VEL, _VEL, (-MAX_OMEGA, MAX_OMEGA)])
    if "physics" in value:
        out["physics"] = validate_physics(value["physics"], f"{name}.physics")
    return out


def validate_action_prefix(value: Any, name: str = "action_prefix") -> list[list[float]]:
    """A list of at most MAX_PREFIX_STEPS absolute targets [x, y] within the world."""
    if not isinstance(value, (list, tuple)):
        raise _bad(f"{name}: expected a list of [x, y], found {type(value).__name__}")
    if len(value) > MAX_PREFIX_STEPS:
        raise _bad(f"{name}: expected at most {MAX_PREFIX_STEPS} steps, found {len(value)}")
    return [_vec(f"{name}[{i}]", a, [_POS, _POS]) for i, a in enumerate(value)]


# --- encoding ---------------------------------------------------------------


# One encoder and one decoder for every message: json.dumps / json.loads with options build a new
# one per call, which showed up on the lease path.
_ENCODER = json.JSONEncoder(allow_nan=False, separators=(",", ":"))


def encode(obj: dict[str, Any]) -> bytes:
    """Compact JSON bytes (no NaN / Infinity)."""
    return _ENCODER.encode(obj).encode()


def _reject_constant(name: str) -> Any:
    raise ValueError(f"non-finite number {name}")


_DECODER = json.JSONDecoder(parse_constant=_reject_constant)


def decode(data: bytes | bytearray | memoryview | str | None, max_bytes: int = MAX_MESSAGE_BYTES) -> dict[str, Any]:
    """Parse one JSON message: size, JSON object, ``"v"`` == PROTOCOL_VERSION. Returns it without "v"."""
    if data is None:
        raise ProtocolError(ErrorCode.BAD_JSON, "expected a JSON message, found no payload")
    raw = data.encode() if isinstance(data, str) else bytes(data)
    if len(raw) > max_bytes:
        raise ProtocolError(ErrorCode.TOO_LARGE, f"expected at most {max_bytes} bytes, found {len(raw)}")
    try:  # what json.loads does with bytes, without building a decoder per call
        obj = _DECODER.decode(raw.decode(json.detect_encoding(raw), "surrogatepass"))
    except (UnicodeDecodeError, ValueError) as exc:
        raise ProtocolError(ErrorCode.BAD_JSON, f"expected a JSON object: {exc}") from None
    if not isinstance(obj, dict):
        raise ProtocolError(ErrorCode.BAD_JSON, f"expected a JSON object, found {type(obj).__name__}")
    version = obj.pop("v", None)
    if version != PROTOCOL_VERSION or isinstance(version, bool):
        raise ProtocolError(ErrorCode.BAD_VERSION, f"expected \"v\": {PROTOCOL_VERSION}, found {version!r:.40}")
    return obj


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
            raise _bad(f"{cls.__name__}: expected a JSON object, found {type(obj).__name__}")
        _, names, required = _field_names(cls)
        if not names.issuperset(obj):
            unknown = sorted(set(obj) - names, key=str)
            raise _bad(f"{cls.__name__}: unknown field(s) {', '.join(map(str, unknown))[:200]}")
        if not required.issubset(obj):
            missing = [f.name for f in dataclasses.fields(cls) if f.name in required and f.name not in obj]
            raise _bad(f"{cls.__name__}: missing field(s) {', '.join(missing)}")
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

    def validate(self) -> None:
        check_id("worker_id", self.worker_id)
        self.tasks = _str_list("tasks", self.tasks, TASKS)
        self.shapes = _str_list("shapes", self.shapes, SHAPES)


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

    def validate(self) -> None:
        check_id("request_id", self.request_id)
        _check_collection(self)
        self.model_version = _str("model_version", self.model_version, allow_empty=True)
        self.token = _int("token", self.token, 1, 2**62)
        self.expires_at = _float("expires_at", self.expires_at, 0.0)
        self.lease_s = _float("lease_s", self.lease_s, 0.001, 86400.0)
        self.seed = _int("seed", self.seed, 0, 2**32 - 1)


def _check_collection(msg: Any) -> None:
    """Shared checks of what a request asks for (LeaseGrant, RequestSpec)."""
    msg.task = _str("task", msg.task, choices=TASKS)
    msg.shape = _str("shape", msg.shape, choices=SHAPES)
    msg.start_state = validate_start_state(msg.start_state)
    if msg.start_state["shape"] != msg.shape:
        raise _bad(f"start_state.shape: expected {msg.shape!r} (the request's shape), "
                   f"found {msg.start_state['shape']!r}")
    msg.policy = _str("policy", msg.policy, choices=POLICIES)
    msg.policy_params = _obj("policy_params", msg.policy_params)
    msg.action_prefix = validate_action_prefix(msg.action_prefix)
    msg.steps = _int("steps", msg.steps, 1, MAX_EPISODE_STEPS)


@dataclass
class LeaseRef(Message):
    """The lease a worker's message is about: the request, the fencing token, the worker holding it."""

    request_id: str
    token: int
    worker_id: str

    def validate(self) -> None:
        check_id("request_id", self.request_id)
        self.token = _int("token", self.token, 1, 2**62)
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
        if not isinstance(self.sha256, str) or not _SHA256_RE.match(self.sha256):
            raise _bad(f"sha256: expected 64 lower-case hex digits, found {self.sha256!r:.80}")
        if isinstance(self.size, int) and not isinstance(self.size, bool) and self.size > MAX_UPLOAD_BYTES:
            raise ProtocolError(ErrorCode.TOO_LARGE,
                                f"size: expected at most {MAX_UPLOAD_BYTES} bytes, found {self.size}")
        self.size = _int("size", self.size, 1, MAX_UPLOAD_BYTES)

    @classmethod
    def for_payload(cls, payload: bytes, *, request_id: str, token: int, worker_id: str) -> UploadHeader:
        """The header of an upload of ``payload`` (computes size and sha256)."""
        return cls(request_id=request_id, token=token, worker_id=worker_id,
                   sha256=hashlib.sha256(payload).hexdigest(), size=len(payload))

    def check_payload(self, payload: bytes | bytearray | memoryview | None) -> bytes:
        """The payload as bytes if it matches this header; ProtocolError too_large / bad_field / hash_mismatch."""
        if payload is None:
            raise _bad("payload: expected the episode's MCAP bytes, found none")
        if len(payload) > MAX_UPLOAD_BYTES:
            raise ProtocolError(ErrorCode.TOO_LARGE,
                                f"payload: expected at most {MAX_UPLOAD_BYTES} bytes, found {len(payload)}")
        data = bytes(payload)
        if len(data) != self.size:
            raise _bad(f"payload: expected {self.size} bytes (header size), found {len(data)}")
        digest = hashlib.sha256(data).hexdigest()
        if digest != self.sha256:
            raise ProtocolError(ErrorCode.HASH_MISMATCH, f"payload: expected sha256 {self.sha256}, found {digest}")
        return data


@dataclass
class FailRequest(LeaseRef):
    """Worker -> ``NS/orch/fail``: give the lease back with an error (counts an attempt)."""

    error: str

    def validate(self) -> None:
        super().validate()
        self.error = _str("error", self.error, max_len=MAX_ERROR_CHARS)


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
        self.priority = _float("priority", self.priority, -1e12, 1e12)
        self.reason = _obj("reason", self.reason)
        self.max_attempts = _int("max_attempts", self.max_attempts, 1, MAX_ATTEMPTS)
        if self.idempotency_key is not None:
            self.idempotency_key = _str("idempotency_key", self.idempotency_key, max_len=256)


#: Operations served under ``NS/admin/**`` (see orchestrator.admin).
ADMIN_OPS: tuple[str, ...] = (
    "queue.ls", "queue.show", "queue.add", "queue.cancel", "queue.retry", "queue.prioritize",
    "workers.ls", "stats", "models.ls",
)


@dataclass
class AdminRequest(Message):
    """Operator -> ``NS/admin/<op>``: one admin operation with its arguments."""

    op: str
    args: dict[str, Any] = field(default_factory=dict)

    def validate(self) -> None:
        if not isinstance(self.op, str) or self.op not in ADMIN_OPS:
            raise ProtocolError(ErrorCode.UNKNOWN_OP,
                                f"op: expected one of {', '.join(ADMIN_OPS)}, found {self.op!r:.80}")
        self.args = _obj("args", self.args)


class EventKind(str, Enum):
    """What an event on ``NS/events/**`` reports."""

    REQUEST_QUEUED = "request.queued"
    REQUEST_LEASED = "request.leased"
    REQUEST_DONE = "request.done"
    REQUEST_FAILED = "request.failed"
    """A lease ended without an episode (fail, expiry, worker loss) and the request went back to queued."""
    REQUEST_DEAD = "request.dead"
    REQUEST_RELEASED = "request.released"
    """A draining worker gave its lease back unharmed: queued again, no attempt counted."""
    REQUEST_CANCELLED = "request.cancelled"
    REQUEST_RETRIED = "request.retried"
    REQUEST_PRIORITIZED = "request.prioritized"
    EPISODE_STORED = "episode.stored"
    EPISODE_REJECTED = "episode.rejected"
    MODEL_TRAINED = "model.trained"
    MODEL_PROMOTED = "model.promoted"
    MODEL_REJECTED = "model.rejected"
    MODEL_ROLLED_BACK = "model.rolled_back"
    WORKER_JOINED = "worker.joined"
    WORKER_LOST = "worker.lost"


_EVENT_PATHS = {kind: kind.value.replace(".", "/") for kind in EventKind}


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
            raise _bad(f"kind: expected one of {', '.join(k.value for k in EventKind)}, "
                       f"found {self.kind!r:.80}") from None
        self.at = _float("at", self.at, 0.0)
        self.data = _obj("data", self.data)


# --- replies -------------------------------------------------------------------


def ok_reply(**body: Any) -> bytes:
    """A success reply: ``{"v": 1, "ok": true, ...body}``."""
    return encode({"v": PROTOCOL_VERSION, "ok": True, **body})


def error_reply(code: ErrorCode | str, message: str) -> bytes:
    """An error reply: ``{"v": 1, "ok": false, "error": code, "message": ...}``."""
    return encode({"v": PROTOCOL_VERSION, "ok": False, "error": ErrorCode(code).value,
                   "message": str(message)[:MAX_ERROR_CHARS]})


def duplicate_reply(**body: Any) -> bytes:
    """A repeated message that was already applied: success, flagged ``"duplicate": true``."""
    return ok_reply(duplicate=True, **body)


def parse_reply(data: bytes | bytearray | memoryview | str | None) -> dict[str, Any]:
    """The body of a reply (without v / ok); an error reply raises ProtocolError with its code."""
    obj = decode(data)
    ok = obj.pop("ok", None)
    if ok is True:
        return obj
    if ok is False:
        code, message = obj.get("error"), str(obj.get("message", ""))
        known = {c.value for c in ErrorCode}
        if code not in known:
            raise ProtocolError(ErrorCode.INTERNAL, f"unknown error code {code!r:.40}: {message:.200}")
        raise ProtocolError(code, message)
    raise ProtocolError(ErrorCode.BAD_FIELD, f"reply: expected \"ok\": true or false, found {ok!r:.40}")
