"""Episodes on disk: one MCAP file per episode, its format and its writer.

Layout of a file (written with the official ``mcap`` package):

- ``/camera``: one ``foxglove.RawImage`` (protobuf, encoding ``rgb8``) per step, so
  the file opens in Foxglove's Image panel. Raw pixels in lz4 chunks cost a few
  microseconds per frame (the flat-coloured frames shrink ~27x); a
  ``CompressedImage`` PNG costs ~170-230 us per frame to encode with OpenCV even at
  level 1, more than simulating and rendering the step.
- ``/action``: ``activecollect.Action`` ``{float x, y}`` per step (protobuf).
- ``/state``: ``activecollect.State``, one ``double`` per ``records.STATE_FIELDS`` entry (protobuf).
  Both schemas travel in the file, so Foxglove plots ``/state.obj_x``. They are encoded
  for the whole episode at once with numpy (every field written explicitly, which any
  protobuf parser accepts); JSON cost ~5 us per step and was the largest Python cost.
- metadata record ``episode``: ``{"json": EpisodeMeta.to_json(), "format", "frames",
  ...}``; only ``json`` is authoritative, the flat keys are for people browsing.

Every message's ``sequence`` is its step index and its log time is
``step / control_hz`` seconds. Chunks (lz4) carry CRCs of their uncompressed content,
the DataEnd record a CRC of the whole data section and the footer a CRC of the
summary, so any flipped bit is found before a byte is decoded.

Here: the topics and schemas, the bytes of each message (``image_prefix``, ``timestamp_field``,
``row_dtype``, ``tag``), what the metadata must hold (``check_meta``), and writing (``encode_episode``,
``write_episode``). Reading a file back and validating it is ``storage.episode_reader``'s, which
recognises these bytes.

Cost at 96x96 on the 2-core dev box (CPU time, 100-step push episodes): encoding
~21 us per frame (lz4 ~4, CRC ~4, mcap's Writer ~3 per message, the rest copies).
"""

from __future__ import annotations

import functools
import io
import math
import os

import numpy as np
from foxglove_schemas_protobuf.RawImage_pb2 import RawImage
from google.protobuf import descriptor_pb2, descriptor_pool
from google.protobuf.message_factory import GetMessageClass
from google.protobuf.timestamp_pb2 import Timestamp
from mcap.writer import CompressionType, Writer
from mcap_protobuf.schema import build_file_descriptor_set

from storage.errors import CorruptEpisodeError, EpisodeError
from storage.files import sha256_hex, write_bytes_atomic
from storage.records import (ACTION_DIM, MAX_META_BYTES, MAX_META_CHARS, STATE_DIM, STATE_FIELDS, Episode,
                             EpisodeMeta)

TOPIC_CAMERA = "/camera"
TOPIC_ACTION = "/action"
TOPIC_STATE = "/state"
METADATA_NAME = "episode"
#: Value of the ``format`` key in the ``episode`` metadata record.
FORMAT = "activecollect.episode/1"
CAMERA_FRAME_ID = "camera"
IMAGE_SCHEMA = RawImage.DESCRIPTOR.full_name  # "foxglove.RawImage"
ACTION_SCHEMA = "activecollect.Action"
STATE_SCHEMA = "activecollect.State"
ACTION_KEYS = ("x", "y")
#: Chunk compression. At 96x96, lz4 costs ~4 us per frame and zstd (level 3, what mcap uses)
#: ~7; zstd files are ~35% smaller. Writing speed matters more here than disk.
COMPRESSION = CompressionType.LZ4
CHUNK_SIZE = 1 << 20
ACTION_SCALAR, STATE_SCALAR = "<f4", "<f8"  # protobuf float, double


def _numeric_messages_file() -> descriptor_pb2.FileDescriptorProto:
    """Protobuf schemas of the action and state messages: one scalar field per column."""
    f = descriptor_pb2.FieldDescriptorProto
    proto = descriptor_pb2.FileDescriptorProto(name="activecollect/episode.proto",
                                               package="activecollect", syntax="proto3")
    for name, keys, kind in (("Action", ACTION_KEYS, f.TYPE_FLOAT), ("State", STATE_FIELDS, f.TYPE_DOUBLE)):
        msg = proto.message_type.add(name=name)
        for number, key in enumerate(keys, start=1):
            msg.field.add(name=key, number=number, type=kind, label=f.LABEL_OPTIONAL)
    return proto


_NUMERIC_FILE = _numeric_messages_file()
_POOL = descriptor_pool.DescriptorPool()
_POOL.Add(_NUMERIC_FILE)
ActionMessage = GetMessageClass(_POOL.FindMessageTypeByName(ACTION_SCHEMA))
StateMessage = GetMessageClass(_POOL.FindMessageTypeByName(STATE_SCHEMA))
_NUMERIC_SCHEMA_DATA = descriptor_pb2.FileDescriptorSet(file=[_NUMERIC_FILE]).SerializeToString()
_IMAGE_SCHEMA_DATA = build_file_descriptor_set(RawImage).SerializeToString()


# ---------------------------------------------------------------------------------------------
# the bytes of one message (storage.episode_reader recognises them)


def _varint(value: int) -> bytes:
    out = bytearray()
    while value >= 0x80:
        out.append((value & 0x7F) | 0x80)
        value >>= 7
    out.append(value)
    return bytes(out)


def image_prefix(height: int, width: int) -> bytes:
    """Serialized RawImage fields shared by every frame, plus the tag and length of ``data``.

    A frame's message is its timestamp field + this prefix + the pixels: protobuf allows
    fields in any order, and this avoids copying the pixels into a message object
    (setting ``RawImage.data`` costs ~12 us at 96x96; the join below ~0.5 us).
    """
    fixed = RawImage(frame_id=CAMERA_FRAME_ID, width=width, height=height,
                     encoding="rgb8", step=width * 3).SerializeToString()
    return fixed + b"\x32" + _varint(height * width * 3)  # field 6 (data), wire type 2


@functools.lru_cache(maxsize=4096)  # step times repeat from episode to episode
def timestamp_field(ns: int) -> bytes:
    """A RawImage's ``timestamp`` field (tag, length, Timestamp) for a log time of ``ns``."""
    ts = Timestamp()
    ts.FromNanoseconds(ns)
    body = ts.SerializeToString()
    return b"\x0a" + _varint(len(body)) + body  # field 1 (timestamp), wire type 2


def row_dtype(k: int, scalar: str) -> np.dtype:
    """One serialized message with fields 1..k, each a tag byte then a ``scalar`` (``<f4``/``<f8``)."""
    return np.dtype([(f, t) for i in range(k) for f, t in ((f"k{i}", "u1"), (f"v{i}", scalar))])


def tag(number: int, scalar: str) -> int:
    """The tag byte of field ``number`` holding a ``scalar`` (``<f4``/``<f8``)."""
    return (number << 3) | (5 if scalar == "<f4" else 1)  # wire type 5: fixed32, 1: fixed64


# ---------------------------------------------------------------------------------------------
# what the metadata must hold (checked on writing and on reading)


_META_TYPES: dict[str, tuple[type, ...]] = {
    "episode_id": (str,), "task": (str,), "shape": (str,), "physics": (dict,), "seed": (int,),
    "policy": (str,), "policy_params": (dict,), "start_state": (dict,), "action_prefix_len": (int,),
    "image_size": (int,), "control_hz": (int, float), "worker_id": (str,), "request_id": (str,),
    "model_version": (str,), "software_version": (str,), "created": (str,),
}


def check_meta(meta: EpisodeMeta, frames: int, name: str,
               error: type[EpisodeError] = CorruptEpisodeError) -> None:
    """``error`` (named ``name``) unless every field of ``meta`` has its type, no string field is longer than
    ``MAX_META_CHARS``, physics are finite numbers and the sizes and ``frames`` are positive."""
    for key, types in _META_TYPES.items():
        value = getattr(meta, key)
        if isinstance(value, bool) or not isinstance(value, types):
            raise error(f"{name}: episode metadata field {key} is {type(value).__name__} "
                                      f"{value!r:.60}, expected {' or '.join(t.__name__ for t in types)}")
    long = [key for key, types in _META_TYPES.items() if types == (str,) and len(getattr(meta, key)) > MAX_META_CHARS]
    if long:
        raise error(f"{name}: episode metadata field {long[0]} has {len(getattr(meta, long[0]))} characters, "
                    f"expected at most {MAX_META_CHARS}")
    bad_physics = [k for k, v in meta.physics.items()
                   if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v)]
    if bad_physics:
        raise error(f"{name}: episode metadata physics {bad_physics} are not finite numbers")
    if meta.image_size <= 0 or not meta.control_hz > 0 or frames <= 0 or meta.action_prefix_len < 0:
        raise error(f"{name}: episode metadata has image_size={meta.image_size}, control_hz="
                                  f"{meta.control_hz}, frames={frames}, action_prefix_len={meta.action_prefix_len}; "
                                  "expected positive numbers")


# ---------------------------------------------------------------------------------------------
# writing


def step_times_ns(steps: int, control_hz: float) -> list[int]:
    """Log time of each step in nanoseconds: ``t / control_hz`` seconds."""
    if not control_hz > 0:
        raise EpisodeError(f"control_hz must be > 0, found {control_hz}")
    period = 1e9 / control_hz
    return [round(t * period) for t in range(steps)]


def _packed_rows(values: np.ndarray, scalar: str) -> bytes:
    """Serializes each row of ``values`` (T, K) as a protobuf message with fields 1..K.

    Every message has the same length (K tags + K scalars), so row ``t`` is the slice
    ``[t * L, (t + 1) * L)`` of the result.
    """
    k = values.shape[1]
    rows = np.empty(len(values), row_dtype(k, scalar))
    for i in range(k):
        rows[f"k{i}"] = tag(i + 1, scalar)
        rows[f"v{i}"] = values[:, i]
    return rows.tobytes()


def _check_writable(ep: Episode) -> None:
    if len(ep) == 0:
        raise EpisodeError(f"episode {ep.meta.episode_id} has no steps; nothing to write")
    check_meta(ep.meta, len(ep), f"episode {ep.meta.episode_id}", EpisodeError)
    size = len(ep.meta.to_json())  # (a read's EpisodeMeta.from_json checks the same of the text it parses)
    if size > MAX_META_BYTES:
        raise EpisodeError(f"episode {ep.meta.episode_id}: metadata takes {size} bytes, expected at most "
                           f"{MAX_META_BYTES}")
    if not np.isfinite(ep.actions).all():
        raise EpisodeError(f"episode {ep.meta.episode_id}: actions must be finite")
    if not np.isfinite(ep.states).all():
        raise EpisodeError(f"episode {ep.meta.episode_id}: states must be finite")
    height, width = ep.frames.shape[1:3]
    if (height, width) != (ep.meta.image_size, ep.meta.image_size):
        raise EpisodeError(f"episode {ep.meta.episode_id}: frames are {height}x{width}, "
                           f"meta.image_size says {ep.meta.image_size}")


def _metadata_record(ep: Episode) -> dict[str, str]:
    m = ep.meta
    flat = {key: str(getattr(m, key)) for key in (
        "episode_id", "task", "shape", "policy", "seed", "request_id", "worker_id",
        "model_version", "software_version", "created")}
    return {**flat, "format": FORMAT, "frames": str(len(ep)), "json": m.to_json()}


def encode_episode(ep: Episode) -> bytes:
    """The episode as a complete MCAP file in memory (same episode, same bytes).

    Raises ``EpisodeError`` for non-finite actions/states or frames whose size
    disagrees with ``meta.image_size``.
    """
    _check_writable(ep)
    buf = io.BytesIO()
    writer = Writer(buf, chunk_size=CHUNK_SIZE, compression=COMPRESSION,
                    enable_crcs=True, enable_data_crcs=True)
    writer.start()
    image_id = writer.register_schema(IMAGE_SCHEMA, "protobuf", _IMAGE_SCHEMA_DATA)
    action_id = writer.register_schema(ACTION_SCHEMA, "protobuf", _NUMERIC_SCHEMA_DATA)
    state_id = writer.register_schema(STATE_SCHEMA, "protobuf", _NUMERIC_SCHEMA_DATA)
    camera = writer.register_channel(TOPIC_CAMERA, "protobuf", image_id)
    action = writer.register_channel(TOPIC_ACTION, "protobuf", action_id)
    state = writer.register_channel(TOPIC_STATE, "protobuf", state_id)
    writer.add_metadata(METADATA_NAME, _metadata_record(ep))

    frames = np.ascontiguousarray(ep.frames)
    prefix = image_prefix(frames.shape[1], frames.shape[2])
    actions = _packed_rows(ep.actions, ACTION_SCALAR)
    states = _packed_rows(ep.states, STATE_SCALAR)
    a_len = row_dtype(ACTION_DIM, ACTION_SCALAR).itemsize
    s_len = row_dtype(STATE_DIM, STATE_SCALAR).itemsize
    add = writer.add_message
    for t, ns in enumerate(step_times_ns(len(ep), ep.meta.control_hz)):
        add(camera, ns, b"".join((timestamp_field(ns), prefix, frames[t].data)), ns, t)
        add(action, ns, actions[t * a_len:(t + 1) * a_len], ns, t)
        add(state, ns, states[t * s_len:(t + 1) * s_len], ns, t)
    writer.finish()
    return buf.getvalue()


def write_episode(path: str | os.PathLike, ep: Episode) -> str:
    """Encodes ``ep`` and writes it atomically to ``path``; returns the file's sha256 (hex)."""
    data = encode_episode(ep)
    write_bytes_atomic(path, data)
    return sha256_hex(data)
