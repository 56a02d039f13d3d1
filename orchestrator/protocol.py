"""The wire contract between orchestrator, workers and operators: the format.

A leaf module: it imports nothing else of ours, so workers on any host can
depend on it without pulling in the service. The messages themselves (one
dataclass per kind of message) live in ``orchestrator.messages``, which
imports only this module.

Section 1 (this header) is the task space: what a collection request may ask
for. Both the uniform planner (which samples it) and the simulator (which
builds worlds from it) read these constants, so they cannot drift apart.
"""

from __future__ import annotations

import json
import math
import re
from dataclasses import dataclass
from datetime import datetime
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
#: Hard caps used by validation. The fewest steps a requested episode may have: a model learns from
#: its context frames and the next one (``uncertainty.config.TrainConfig.context`` + 1; this module
#: imports nothing of ours, a test keeps the two equal): a shorter episode gives no training window.
MIN_EPISODE_STEPS, MAX_EPISODE_STEPS = 3, 1000
#: Frame sizes an episode may have (what the simulator renders; storage.records holds the same limits, a
#: test keeps them equal, and the narrower ``trainable_size``: what a model trains on).
MIN_FRAME_SIZE, MAX_FRAME_SIZE = 8, 1024
MAX_PREFIX_STEPS = 1000

# ---------------------------------------------------------------------------
# Section 2: the format every message shares: limits, error codes, the key space,
# field checks, JSON encoding and replies. orchestrator.messages builds on it.
#
# Every reply is {"v": 1, "ok": true, ...body} or {"v": 1, "ok": false, "error": code,
# "message": why} (ok_reply / error_reply / parse_reply); orchestrator.messages lists
# which message and which reply each key takes.
# ---------------------------------------------------------------------------

#: Version every JSON message carries as ``"v"``; a message with another version is refused.
PROTOCOL_VERSION = 1
#: Largest JSON message (query payload, attachment, reply) accepted, in bytes.
MAX_MESSAGE_BYTES = 256 * 1024
#: Largest episode upload (raw MCAP bytes), in bytes.
MAX_UPLOAD_BYTES = 64 * 1024 * 1024
#: Largest encoded ``policy_params`` / ``reason`` / admin ``args`` / event ``data`` object, in bytes.
MAX_OBJECT_BYTES = 16 * 1024
#: Deepest nesting of lists / objects a ``policy_params`` / ``reason`` / admin ``args`` / event ``data``
#: object may have (deeper ones break recursive copies and encoders further on).
MAX_OBJECT_DEPTH = 32
#: Largest error text a worker may report.
MAX_ERROR_CHARS = 4096
#: Largest |velocity| in a start state (world units/s) and |angular velocity| (rad/s).
MAX_SPEED = 10 * WORLD_SIZE
MAX_OMEGA = 100.0
#: Most tasks / shapes a worker may declare.
MAX_CAPABILITIES = 32
#: Most attempts a request may be given.
MAX_ATTEMPTS = 100
#: Largest priority (either sign) a request may be given.
MAX_PRIORITY = 1e12

_ID_RE = re.compile(r"^[A-Za-z0-9_.\-]{1,128}$")
_NAMESPACE_RE = re.compile(r"^[A-Za-z0-9_\-]+(/[A-Za-z0-9_\-]+)*$")


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


def bad_field(message: str) -> ProtocolError:
    """A ProtocolError with code bad_field (what every field check raises)."""
    return ProtocolError(ErrorCode.BAD_FIELD, message)


# --- keys -------------------------------------------------------------------


def check_id(name: str, value: Any) -> str:
    """A request / worker / episode id: 1-128 chars of ``[A-Za-z0-9_.-]`` (safe as one key chunk)."""
    if not isinstance(value, str) or not _ID_RE.fullmatch(value):
        raise bad_field(f"{name}: expected 1-128 characters of [A-Za-z0-9_.-], found {value!r:.80}")
    return value


#: Operations served under ``NS/admin/**`` (see orchestrator.admin).
ADMIN_OPS: tuple[str, ...] = (
    "queue.ls", "queue.show", "queue.add", "queue.cancel", "queue.retry", "queue.prioritize",
    "workers.ls", "stats", "models.ls",
)


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


@dataclass(frozen=True)
class Keys:
    """The Zenoh key space of one deployment, under ``namespace``."""

    namespace: str = "activecollect"
    """Prefix of every key: chunks of ``[A-Za-z0-9_-]`` joined by ``/``, no wildcards."""

    def __post_init__(self) -> None:
        if not isinstance(self.namespace, str) or not _NAMESPACE_RE.fullmatch(self.namespace):
            raise bad_field(f"namespace: expected chunks of [A-Za-z0-9_-] joined by '/', "
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
            raise bad_field(f"expected a key under {prefix}, found {key!r}")
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
            raise bad_field(f"expected an event key under {prefix}, found {key!r}")
        return EventKind(kind)


# --- field checks -----------------------------------------------------------


def check_str(name: str, value: Any, *, max_len: int = 128, choices: tuple[str, ...] | None = None,
              allow_empty: bool = False) -> str:
    """A string of 1-``max_len`` characters (0 allowed with ``allow_empty``), one of ``choices`` if given."""
    if not isinstance(value, str):
        raise bad_field(f"{name}: expected a string, found {type(value).__name__}")
    if len(value) > max_len or (not value and not allow_empty):
        raise bad_field(f"{name}: expected 1-{max_len} characters, found {len(value)}")
    if choices is not None and value not in choices:
        raise bad_field(f"{name}: expected one of {', '.join(choices)}, found {value!r:.80}")
    return value


def check_int(name: str, value: Any, lo: int, hi: int) -> int:
    """An integer (not a bool) in [lo, hi]."""
    if isinstance(value, bool) or not isinstance(value, int):
        raise bad_field(f"{name}: expected an integer, found {type(value).__name__}")
    if not lo <= value <= hi:
        raise bad_field(f"{name}: expected an integer in [{lo}, {hi}], found {value}")
    return value


def check_float(name: str, value: Any, lo: float = -math.inf, hi: float = math.inf) -> float:
    """A finite number (int or float, not a bool) in [lo, hi], returned as a float."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise bad_field(f"{name}: expected a number, found {type(value).__name__}")
    try:
        value = float(value)
    except OverflowError:  # an integer literal of hundreds of digits
        raise bad_field(f"{name}: expected a finite number in [{lo:g}, {hi:g}], found an integer of "
                        f"{value.bit_length()} bits") from None
    if not math.isfinite(value) or not lo <= value <= hi:
        raise bad_field(f"{name}: expected a finite number in [{lo:g}, {hi:g}], found {value!r}")
    return value


def check_vec(name: str, value: Any, bounds: list[tuple[float, float]]) -> list[float]:
    """A list of ``len(bounds)`` numbers, each within its (lo, hi)."""
    if not isinstance(value, (list, tuple)) or len(value) != len(bounds):
        raise bad_field(f"{name}: expected a list of {len(bounds)} numbers, found {value!r:.80}")
    return [check_float(f"{name}[{i}]", v, lo, hi) for i, (v, (lo, hi)) in enumerate(zip(value, bounds))]


def _nests_deeper(value: Any, limit: int) -> bool:
    """Whether lists / dicts nest more than ``limit`` deep in ``value``: depth first, without recursion,
    stopping at the first branch past the limit (so a cycle ends too)."""
    stack = [(value, 1)]
    while stack:
        item, depth = stack.pop()
        if not isinstance(item, (dict, list, tuple)):
            continue
        if depth > limit:
            return True
        stack.extend((child, depth + 1) for child in (item.values() if isinstance(item, dict) else item))
    return False


def check_obj(name: str, value: Any, max_bytes: int = MAX_OBJECT_BYTES) -> dict[str, Any]:
    """A JSON object with string keys and finite values, at most ``max_bytes`` encoded (else too_large)
    and nested at most MAX_OBJECT_DEPTH deep."""
    if not isinstance(value, dict) or not all(isinstance(k, str) for k in value):
        raise bad_field(f"{name}: expected a JSON object with string keys, found {type(value).__name__}")
    if _nests_deeper(value, MAX_OBJECT_DEPTH):
        raise bad_field(f"{name}: expected lists / objects nested at most {MAX_OBJECT_DEPTH} deep, found deeper")
    try:
        size = len(json.dumps(value, allow_nan=False, separators=(",", ":")))
    except (TypeError, ValueError) as exc:
        raise bad_field(f"{name}: expected JSON-encodable finite values ({exc})") from None
    if size > max_bytes:
        raise ProtocolError(ErrorCode.TOO_LARGE, f"{name}: expected at most {max_bytes} bytes, found {size}")
    return dict(value)


def check_str_list(name: str, value: Any, choices: tuple[str, ...]) -> list[str]:
    """A list of at most MAX_CAPABILITIES strings, each one of ``choices``."""
    if not isinstance(value, (list, tuple)) or len(value) > MAX_CAPABILITIES:
        raise bad_field(f"{name}: expected a list of at most {MAX_CAPABILITIES} strings, found {value!r:.80}")
    return [check_str(f"{name}[{i}]", v, choices=choices) for i, v in enumerate(value)]


_POS = (0.0, WORLD_SIZE)
_VEL = (-MAX_SPEED, MAX_SPEED)
_ANGLE = (-1e6, 1e6)
_START_KEYS = {"shape", "agent", "agent_vel", "object", "object_vel", "physics"}


def validate_physics(value: Any, name: str = "physics") -> dict[str, float]:
    """Physics parameters: a subset of PHYSICS_RANGES' keys, each within its (low, high)."""
    value = check_obj(name, value)
    unknown = sorted(set(value) - set(PHYSICS_RANGES))
    if unknown:
        raise bad_field(f"{name}: expected keys among {', '.join(PHYSICS_RANGES)}, found {', '.join(unknown)}")
    return {k: check_float(f"{name}.{k}", v, *PHYSICS_RANGES[k][:2]) for k, v in value.items()}


def physics_problem(physics: Any) -> str:
    """Why an episode's physics are outside the task space ('' when inside): the planner turns an
    episode's physics into new requests, which workers must be able to take."""
    try:
        validate_physics(physics)
    except ProtocolError as exc:
        return f"{exc.message} (outside the task space)"
    return ""


def episode_problem(meta: Any) -> str:
    """Why an episode's metadata (a ``storage.records.EpisodeMeta``) is outside the task space ('' when
    inside): a task and shape of ours, a ``created`` time in ISO 8601 (or '', unknown), physics a worker
    can run. What enters the catalog by upload or ingest; the planner turns episodes into requests."""
    for name, choices in (("task", TASKS), ("shape", SHAPES)):
        if getattr(meta, name) not in choices:
            return f"{name}: expected one of {', '.join(choices)}, found {one_line(repr(getattr(meta, name)))[:60]}"
    try:
        if meta.created != "":
            datetime.fromisoformat(meta.created)
    except (TypeError, ValueError):
        return f"created: expected an ISO 8601 time, found {one_line(repr(meta.created))[:60]}"
    return physics_problem(meta.physics)


def validate_start_state(value: Any, name: str = "start_state") -> dict[str, Any]:
    """A simulator state in ``SimState.to_dict`` form, inside the task space; returns a clean copy.

    Required: shape (in SHAPES), agent [x, y], object [x, y, theta] (positions within the world).
    Optional: agent_vel [vx, vy], object_vel [vx, vy, omega], physics. Raises ProtocolError(bad_field).
    """
    value = check_obj(name, value)
    unknown = sorted(set(value) - _START_KEYS)
    missing = sorted({"shape", "agent", "object"} - set(value))
    if unknown or missing:
        raise bad_field(f"{name}: expected keys {', '.join(sorted(_START_KEYS))} (shape, agent, object "
                        f"required); unknown {unknown}, missing {missing}")
    out: dict[str, Any] = {"shape": check_str(f"{name}.shape", value["shape"], choices=SHAPES),
                           "agent": check_vec(f"{name}.agent", value["agent"], [_POS, _POS]),
                           "object": check_vec(f"{name}.object", value["object"], [_POS, _POS, _ANGLE])}
    if "agent_vel" in value:
        out["agent_vel"] = check_vec(f"{name}.agent_vel", value["agent_vel"], [_VEL, _VEL])
    if "object_vel" in value:
        out["object_vel"] = check_vec(f"{name}.object_vel", value["object_vel"],
                                      [_VEL, _VEL, (-MAX_OMEGA, MAX_OMEGA)])
    if "physics" in value:
        out["physics"] = validate_physics(value["physics"], f"{name}.physics")
    return out


def validate_action_prefix(value: Any, name: str = "action_prefix") -> list[list[float]]:
    """A list of at most MAX_PREFIX_STEPS absolute targets [x, y] within the world."""
    if not isinstance(value, (list, tuple)):
        raise bad_field(f"{name}: expected a list of [x, y], found {type(value).__name__}")
    if len(value) > MAX_PREFIX_STEPS:
        raise bad_field(f"{name}: expected at most {MAX_PREFIX_STEPS} steps, found {len(value)}")
    return [check_vec(f"{name}[{i}]", a, [_POS, _POS]) for i, a in enumerate(value)]


# --- encoding ---------------------------------------------------------------


_CONTROL = re.compile(r"[\x00-\x1f\x7f]")


def one_line(text: str) -> str:
    """``text`` with its control characters escaped (``\\n``): a peer's words in a log line cannot start
    a line of their own."""
    return _CONTROL.sub(lambda m: repr(m.group())[1:-1], text)


# One encoder and one decoder for every message: json.dumps / json.loads with options build a new
# one per call, which showed up on the lease path.
_ENCODER = json.JSONEncoder(allow_nan=False, separators=(",", ":"))
_STRICT_ENCODER = json.JSONEncoder(ensure_ascii=False, separators=(",", ":"))


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
    raw = data.encode("utf-8", "surrogatepass") if isinstance(data, str) else bytes(data)
    if len(raw) > max_bytes:
        raise ProtocolError(ErrorCode.TOO_LARGE, f"expected at most {max_bytes} bytes, found {len(raw)}")
    try:  # UTF-8 only (RFC 8259; json.loads would also take UTF-16/32), strictly: no lone surrogates
        text = raw.decode("utf-8")
        obj = _DECODER.decode(text)
        if "\\u" in text:  # an escape may spell half a surrogate pair, which no UTF-8 string can hold
            _STRICT_ENCODER.encode(obj).encode("utf-8")
    except (UnicodeError, ValueError) as exc:
        raise ProtocolError(ErrorCode.BAD_JSON, f"expected a JSON object: {exc}") from None
    except RecursionError:  # a few thousand brackets fit well under max_bytes
        raise ProtocolError(ErrorCode.BAD_JSON, "expected a JSON object, found lists / objects nested "
                            "too deeply to parse") from None
    if not isinstance(obj, dict):
        raise ProtocolError(ErrorCode.BAD_JSON, f"expected a JSON object, found {type(obj).__name__}")
    version = obj.pop("v", None)
    if type(version) is not int or version != PROTOCOL_VERSION:  # not 1.0, not true
        raise ProtocolError(ErrorCode.BAD_VERSION, f"expected \"v\": {PROTOCOL_VERSION}, found {version!r:.40}")
    return obj


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
    return reply_body(decode(data))


def reply_body(obj: dict[str, Any]) -> dict[str, Any]:
    """``parse_reply`` of a reply already decoded."""
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
