"""Episodes on disk: one MCAP file per episode.

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

Cost at 96x96 on the 2-core dev box (CPU time, 100-step push episodes): encoding
~21 us per frame (lz4 ~4, CRC ~4, mcap's Writer ~3 per message, the rest copies);
reading ~18 us per frame. The reader recognises the exact bytes this writer makes
and skips protobuf parsing for them; any other valid encoding of the same schemas
(another writer's) is parsed with protobuf.
"""

from __future__ import annotations

import functools
import io
import math
import os
import stat
import struct
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Union

import lz4.frame
import numpy as np
import zstandard
from foxglove_schemas_protobuf.RawImage_pb2 import RawImage
from google.protobuf import descriptor_pb2, descriptor_pool
from google.protobuf.message import DecodeError
from google.protobuf.message_factory import GetMessageClass
from google.protobuf.timestamp_pb2 import Timestamp
from mcap.exceptions import McapError
from mcap.opcode import Opcode
from mcap.reader import FOOTER_SIZE, SeekingReader
from mcap.data_stream import ReadDataStream
from mcap.records import Channel, Chunk, Message, Schema, Statistics
from mcap.stream_reader import CRCValidationError
from mcap.writer import CompressionType, Writer
from mcap_protobuf.schema import build_file_descriptor_set

from storage.errors import (
    CorruptEpisodeError,
    EpisodeError,
    ForeignFileError,
    OversizedEpisodeError,
    StorageError,
    TruncatedEpisodeError,
)
from storage.files import sha256_hex, write_bytes_atomic
from storage.records import (ACTION_DIM, MAX_META_BYTES, MAX_META_CHARS, STATE_DIM, STATE_FIELDS, Episode,
                             EpisodeMeta)

Source = Union[str, os.PathLike, bytes, bytearray, memoryview]

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
_ACTION_SCALAR, _STATE_SCALAR = "<f4", "<f8"  # protobuf float, double

MAGIC = b"\x89MCAP0\r\n"
_DATA_END_SIZE = 1 + 8 + 4
_TRAILER_SIZE = FOOTER_SIZE + len(MAGIC)


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
# writing


def _varint(value: int) -> bytes:
    out = bytearray()
    while value >= 0x80:
        out.append((value & 0x7F) | 0x80)
        value >>= 7
    out.append(value)
    return bytes(out)


def _image_prefix(height: int, width: int) -> bytes:
    """Serialized RawImage fields shared by every frame, plus the tag and length of ``data``.

    A frame's message is its timestamp field + this prefix + the pixels: protobuf allows
    fields in any order, and this avoids copying the pixels into a message object
    (setting ``RawImage.data`` costs ~12 us at 96x96; the join below ~0.5 us).
    """
    fixed = RawImage(frame_id=CAMERA_FRAME_ID, width=width, height=height,
                     encoding="rgb8", step=width * 3).SerializeToString()
    return fixed + b"\x32" + _varint(height * width * 3)  # field 6 (data), wire type 2


@functools.lru_cache(maxsize=4096)  # step times repeat from episode to episode
def _timestamp_field(ns: int) -> bytes:
    ts = Timestamp()
    ts.FromNanoseconds(ns)
    body = ts.SerializeToString()
    return b"\x0a" + _varint(len(body)) + body  # field 1 (timestamp), wire type 2


def step_times_ns(steps: int, control_hz: float) -> list[int]:
    """Log time of each step in nanoseconds: ``t / control_hz`` seconds."""
    if not control_hz > 0:
        raise EpisodeError(f"control_hz must be > 0, found {control_hz}")
    period = 1e9 / control_hz
    return [round(t * period) for t in range(steps)]


def _row_dtype(k: int, scalar: str) -> np.dtype:
    """One serialized message with fields 1..k, each a tag byte then a ``scalar`` (``<f4``/``<f8``)."""
    return np.dtype([(f, t) for i in range(k) for f, t in ((f"k{i}", "u1"), (f"v{i}", scalar))])


def _tag(number: int, scalar: str) -> int:
    return (number << 3) | (5 if scalar == "<f4" else 1)  # wire type 5: fixed32, 1: fixed64


def _packed_rows(values: np.ndarray, scalar: str) -> bytes:
    """Serializes each row of ``values`` (T, K) as a protobuf message with fields 1..K.

    Every message has the same length (K tags + K scalars), so row ``t`` is the slice
    ``[t * L, (t + 1) * L)`` of the result.
    """
    k = values.shape[1]
    rows = np.empty(len(values), _row_dtype(k, scalar))
    for i in range(k):
        rows[f"k{i}"] = _tag(i + 1, scalar)
        rows[f"v{i}"] = values[:, i]
    return rows.tobytes()


def _check_writable(ep: Episode) -> None:
    if len(ep) == 0:
        raise EpisodeError(f"episode {ep.meta.episode_id} has no steps; nothing to write")
    _check_meta(ep.meta, len(ep), f"episode {ep.meta.episode_id}", EpisodeError)
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
    prefix = _image_prefix(frames.shape[1], frames.shape[2])
    actions = _packed_rows(ep.actions, _ACTION_SCALAR)
    states = _packed_rows(ep.states, _STATE_SCALAR)
    a_len = _row_dtype(ACTION_DIM, _ACTION_SCALAR).itemsize
    s_len = _row_dtype(STATE_DIM, _STATE_SCALAR).itemsize
    add = writer.add_message
    for t, ns in enumerate(step_times_ns(len(ep), ep.meta.control_hz)):
        add(camera, ns, b"".join((_timestamp_field(ns), prefix, frames[t].data)), ns, t)
        add(action, ns, actions[t * a_len:(t + 1) * a_len], ns, t)
        add(state, ns, states[t * s_len:(t + 1) * s_len], ns, t)
    writer.finish()
    return buf.getvalue()


def write_episode(path: str | os.PathLike, ep: Episode) -> str:
    """Encodes ``ep`` and writes it atomically to ``path``; returns the file's sha256 (hex)."""
    data = encode_episode(ep)
    write_bytes_atomic(path, data)
    return sha256_hex(data)


# ---------------------------------------------------------------------------------------------
# reading


@dataclass
class _Scan:
    """What one pass over a structurally valid MCAP found."""

    schemas: dict[int, Schema] = field(default_factory=dict)
    channels: dict[int, Channel] = field(default_factory=dict)
    messages: dict[int, list[Message]] = field(default_factory=dict)
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)
    statistics: Statistics | None = None


#: No episode file is larger (1,000 steps of 1024 px frames, lz4-compressed, stay well under it): a bigger
#: path is refused before it is read into memory.
MAX_EPISODE_FILE_BYTES = 1 << 30


def read_file(path: Path, error: type[StorageError] = EpisodeError) -> bytes:
    """The bytes of the episode file at ``path``; ``error`` for a missing path, a directory, a pipe or
    device (reading one may never end), a file larger than ``MAX_EPISODE_FILE_BYTES``, a failed read."""
    try:
        st = path.stat()
        if stat.S_ISDIR(st.st_mode):
            raise error(f"{path}: is a directory, expected an MCAP file")
        if not stat.S_ISREG(st.st_mode):
            raise error(f"{path}: is not a regular file (a pipe or a device?), expected an MCAP file")
        if st.st_size > MAX_EPISODE_FILE_BYTES:
            raise error(f"{path}: {st.st_size} bytes, more than any episode (at most {MAX_EPISODE_FILE_BYTES})")
        return path.read_bytes()
    except FileNotFoundError:
        raise error(f"{path}: no such file") from None
    except OSError as exc:
        raise error(f"{path}: cannot read: {exc.strerror or exc}") from exc


def _load(source: Source, name: str | None) -> tuple[bytes, str]:
    if isinstance(source, (bytes, bytearray, memoryview)):
        return bytes(source), name or "<bytes>"
    return read_file(Path(source)), name or str(source)


def _check_envelope(data: bytes, name: str) -> None:
    """Magic, footer, and the summary and data-section CRCs, before anything is decoded."""
    size = len(data)
    if size < len(MAGIC):
        if MAGIC.startswith(data):
            raise TruncatedEpisodeError(f"{name}: {size} bytes, cut off inside the MCAP magic")
        raise ForeignFileError(f"{name}: not an MCAP file ({size} bytes, no MCAP magic)")
    tail_ok = size >= 2 * len(MAGIC) and data[-len(MAGIC):] == MAGIC
    if data[:len(MAGIC)] != MAGIC:
        if tail_ok:
            raise CorruptEpisodeError(f"{name}: damaged opening magic {data[:8]!r}")
        raise ForeignFileError(f"{name}: not an MCAP file (starts with {data[:8]!r}, "
                               f"expected the MCAP magic {MAGIC!r})")
    footer_at = size - _TRAILER_SIZE
    footer_ok = (footer_at >= len(MAGIC) and data[footer_at] == Opcode.FOOTER
                 and struct.unpack_from("<Q", data, footer_at + 1)[0] == FOOTER_SIZE - 9)
    if not footer_ok and not tail_ok:
        raise TruncatedEpisodeError(f"{name}: ends after {size} bytes without an MCAP footer "
                                    "(a partial write or a cut transfer)")
    if not footer_ok:
        raise CorruptEpisodeError(f"{name}: damaged footer record at byte {footer_at}")
    if not tail_ok:
        raise CorruptEpisodeError(f"{name}: damaged closing magic {data[-8:]!r}")
    summary_start, summary_offset_start, summary_crc = struct.unpack_from("<QQI", data, footer_at + 9)
    if summary_start == 0:
        raise ForeignFileError(f"{name}: MCAP file without a summary section "
                               "(activecollect episodes always have one)")
    if not len(MAGIC) + _DATA_END_SIZE <= summary_start <= footer_at:
        raise CorruptEpisodeError(f"{name}: footer points to a summary at byte {summary_start}, "
                                  f"outside the file's {size} bytes")
    if summary_crc != 0:
        found = zlib.crc32(data[summary_start:footer_at + 1 + 8 + 8 + 8])
        if found != summary_crc:
            raise CorruptEpisodeError(f"{name}: summary CRC mismatch (footer says {summary_crc:#010x}, "
                                      f"bytes give {found:#010x})")
    end_at = summary_start - _DATA_END_SIZE
    if data[end_at] != Opcode.DATA_END or struct.unpack_from("<Q", data, end_at + 1)[0] != 4:
        raise CorruptEpisodeError(f"{name}: no DataEnd record before the summary at byte {summary_start}")
    data_crc = struct.unpack_from("<I", data, end_at + 9)[0]
    if data_crc != 0:
        found = zlib.crc32(data[:end_at])
        if found != data_crc:
            raise CorruptEpisodeError(f"{name}: data section CRC mismatch (DataEnd says {data_crc:#010x}, "
                                      f"bytes give {found:#010x})")


#: What one step may add to the chunks besides its pixels: three message records and their framing
#: (ours take ~150 bytes), and what a chunk may hold besides steps (schemas, channels).
STEP_OVERHEAD, CHUNK_OVERHEAD = 1024, 64 * 1024


def decoded_limit(frames: int, image_size: int) -> int:
    """The most bytes the chunks of an episode of ``frames`` steps of ``image_size`` pixels may inflate to."""
    return frames * (3 * image_size * image_size + STEP_OVERHEAD) + CHUNK_OVERHEAD


def _scan(data: bytes, name: str,
          max_decoded: int | None = None) -> tuple[_Scan, EpisodeMeta, int, dict[str, int]]:
    """Summary, metadata, our three channels' ids, and every message, with chunk CRCs checked.

    The chunks are inflated only up to what the metadata's frames and frame size need (and at
    most ``max_decoded`` bytes in all): a small file whose chunk claims gigabytes is refused
    before that memory is taken.
    """
    scan = _Scan()
    reader = SeekingReader(io.BytesIO(data), validate_crcs=True, record_size_limit=len(data))
    try:
        summary = reader.get_summary()
        if summary is None:
            raise ForeignFileError(f"{name}: MCAP file without a summary section")
        scan.schemas, scan.channels, scan.statistics = summary.schemas, summary.channels, summary.statistics
        for record in reader.iter_metadata():
            scan.metadata[record.name] = record.metadata
        meta, frames = _meta(scan, name)
        ids = {TOPIC_CAMERA: _channel(scan, TOPIC_CAMERA, IMAGE_SCHEMA, "protobuf", name),
               TOPIC_ACTION: _channel(scan, TOPIC_ACTION, ACTION_SCHEMA, "protobuf", name),
               TOPIC_STATE: _channel(scan, TOPIC_STATE, STATE_SCHEMA, "protobuf", name)}
        budget = decoded_limit(frames, meta.image_size)
        if max_decoded is not None:
            budget = min(budget, max_decoded)
        _read_chunks(data, summary.chunk_indexes, budget, scan, name)
    except CRCValidationError as exc:
        raise CorruptEpisodeError(f"{name}: {exc}") from exc
    except (McapError, struct.error, ValueError, KeyError, IndexError, TypeError, OverflowError, OSError,
            RuntimeError, zstandard.ZstdError, MemoryError) as exc:
        # The envelope was intact, so a record that does not parse was written that way.
        raise CorruptEpisodeError(f"{name}: undecodable MCAP record: {type(exc).__name__}: {exc}") from exc
    return scan, meta, frames, ids


def _read_chunks(data: bytes, indexes: list, budget: int, scan: _Scan, name: str) -> None:
    """Every message of the indexed chunks into ``scan.messages``, inflating at most ``budget`` bytes."""
    if not indexes:
        raise ForeignFileError(f"{name}: MCAP file without chunk indexes (activecollect episodes have them)")
    offsets = [ix.chunk_start_offset for ix in indexes]
    if len(set(offsets)) != len(offsets):
        raise CorruptEpisodeError(f"{name}: the summary indexes a chunk twice")
    buf = io.BytesIO(data)
    for index in sorted(indexes, key=lambda ix: ix.chunk_start_offset):
        offset = index.chunk_start_offset
        buf.seek(offset)
        stream = ReadDataStream(buf)
        if stream.read1() != Opcode.CHUNK:
            raise CorruptEpisodeError(f"{name}: no chunk at byte {offset}, where the summary indexes one")
        length = stream.read8()
        if length != index.chunk_length - 9 or offset + index.chunk_length > len(data):
            raise CorruptEpisodeError(f"{name}: chunk at byte {offset} says it is {length} bytes long, its index "
                                      f"{index.chunk_length - 9}, in a file of {len(data)} bytes")
        chunk = Chunk.read(stream)
        if stream.count != 9 + length:
            raise CorruptEpisodeError(f"{name}: chunk at byte {offset} holds {stream.count - 9} bytes of "
                                      f"fields, its record {length}")
        if chunk.uncompressed_crc == 0:  # with no CRC, a flipped bit in it could not be found
            raise CorruptEpisodeError(f"{name}: chunk at byte {offset} has no CRC (activecollect writes one)")
        if chunk.uncompressed_size > budget:
            raise OversizedEpisodeError(f"{name}: chunk at byte {offset} inflates to {chunk.uncompressed_size} "
                                        f"bytes; the episode's frames need at most {budget} more")
        body = _inflate(chunk, name)
        budget -= len(body)
        if zlib.crc32(body) != chunk.uncompressed_crc:
            raise CorruptEpisodeError(f"{name}: chunk at byte {offset}: CRC mismatch of its content")
        inner = ReadDataStream(io.BytesIO(body))
        while inner.count < len(body):
            opcode, length = inner.read1(), inner.read8()
            if opcode == Opcode.MESSAGE:
                message = Message.read(inner, length)
                scan.messages.setdefault(message.channel_id, []).append(message)
            else:  # schemas and channels: the summary has them
                inner.read(length)


def _inflate(chunk: Chunk, name: str) -> bytes:
    """A chunk's content, never more than the ``uncompressed_size`` it declares."""
    size = chunk.uncompressed_size
    if chunk.compression == "":
        body = chunk.data
    elif chunk.compression == "lz4":
        body = lz4.frame.LZ4FrameDecompressor().decompress(chunk.data, max_length=size + 1)
    elif chunk.compression == "zstd":
        with zstandard.ZstdDecompressor().stream_reader(chunk.data) as reader:
            body = reader.read(size + 1)
    else:
        raise ForeignFileError(f"{name}: chunk compression {chunk.compression!r} (expected lz4, zstd or none)")
    if len(body) != size:
        raise CorruptEpisodeError(f"{name}: a chunk declares {size} bytes of content and holds "
                                  f"{'more' if len(body) > size else len(body)}")
    return body


def _channel(scan: _Scan, topic: str, schema: str, encoding: str, name: str) -> int:
    found = [c for c in scan.channels.values() if c.topic == topic]
    if not found:
        raise ForeignFileError(f"{name}: no {topic} channel; not an activecollect episode "
                               f"(topics: {sorted(c.topic for c in scan.channels.values())})")
    chan = found[0]
    sch = scan.schemas.get(chan.schema_id)
    if chan.message_encoding != encoding or sch is None or sch.name != schema:
        raise ForeignFileError(f"{name}: {topic} carries {chan.message_encoding!r} "
                               f"{sch.name if sch else 'no schema'!r}, expected {encoding!r} {schema!r}")
    return chan.id


_META_TYPES: dict[str, tuple[type, ...]] = {
    "episode_id": (str,), "task": (str,), "shape": (str,), "physics": (dict,), "seed": (int,),
    "policy": (str,), "policy_params": (dict,), "start_state": (dict,), "action_prefix_len": (int,),
    "image_size": (int,), "control_hz": (int, float), "worker_id": (str,), "request_id": (str,),
    "model_version": (str,), "software_version": (str,), "created": (str,),
}


def _check_meta(meta: EpisodeMeta, frames: int, name: str,
                error: type[EpisodeError] = CorruptEpisodeError) -> None:
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


def _meta(scan: _Scan, name: str) -> tuple[EpisodeMeta, int]:
    record = scan.metadata.get(METADATA_NAME)
    if record is None or record.get("format") != FORMAT:
        raise ForeignFileError(f"{name}: no {METADATA_NAME!r} metadata record of format {FORMAT}; "
                               "not an activecollect episode")
    try:
        meta = EpisodeMeta.from_json(record.get("json", ""))
        frames = int(record.get("frames", ""))
    except ValueError as exc:
        raise CorruptEpisodeError(f"{name}: bad frame count in episode metadata: {exc}") from exc
    except (EpisodeError, TypeError) as exc:
        raise CorruptEpisodeError(f"{name}: {exc}") from exc
    _check_meta(meta, frames, name)
    return meta, frames


def _check_counts(scan: _Scan, ids: dict[str, int], frames: int, name: str) -> None:
    """Every channel holds exactly ``frames`` messages, in step order, as the summary says."""
    stats = scan.statistics
    if stats is None:
        raise CorruptEpisodeError(f"{name}: summary has no statistics record")
    total = sum(len(v) for v in scan.messages.values())
    if stats.message_count != total:
        raise CorruptEpisodeError(f"{name}: summary counts {stats.message_count} messages, "
                                  f"the chunks hold {total}")
    for topic, cid in ids.items():
        msgs = scan.messages.get(cid, [])
        said = stats.channel_message_counts.get(cid, 0)
        if said != len(msgs) or len(msgs) != frames:
            raise CorruptEpisodeError(f"{name}: {topic} holds {len(msgs)} messages, summary says "
                                      f"{said}, metadata says {frames} frames")
        if [m.sequence for m in msgs] != list(range(frames)):
            raise CorruptEpisodeError(f"{name}: {topic} messages are not steps 0..{frames - 1} in order")
        times = [m.log_time for m in msgs]  # ours are step / control_hz; another recorder's clock may differ
        back = next((t for t in range(1, frames) if times[t] <= times[t - 1]), None)
        if back is not None:
            raise CorruptEpisodeError(f"{name}: {topic} step {back} is logged at {times[back]} ns, not after "
                                      f"step {back - 1} ({times[back - 1]} ns)")


def _examine(source: Source, name: str | None,
             max_decoded: int | None = None) -> tuple[_Scan, EpisodeMeta, dict[str, int], str]:
    data, name = _load(source, name)
    _check_envelope(data, name)
    scan, meta, frames, ids = _scan(data, name, max_decoded)
    _check_counts(scan, ids, frames, name)
    return scan, meta, ids, name


def _decode_frames(msgs: list[Message], size: int, name: str) -> np.ndarray:
    pixels = 3 * size * size
    short = next((t for t, m in enumerate(msgs) if len(m.data) < pixels), None)
    if short is not None:  # checked before allocating: a hostile image_size must not cost memory
        raise CorruptEpisodeError(f"{name}: /camera step {short}: {len(msgs[short].data)} bytes cannot hold "
                                  f"a {size}x{size} rgb8 image (metadata image_size {size})")
    out = np.empty((len(msgs), size, size, 3), np.uint8)
    prefix = _image_prefix(size, size)
    image = RawImage()
    for t, msg in enumerate(msgs):
        buf = msg.data
        head = len(buf) - pixels
        # Fast path: exactly the bytes encode_episode writes for this step (no parse, one copy).
        if head >= len(prefix) and buf[head - len(prefix):head] == prefix \
                and buf[:head - len(prefix)] == _timestamp_field(msg.log_time):
            out[t] = np.frombuffer(buf, np.uint8, pixels, head).reshape(size, size, 3)
            continue
        try:
            image.ParseFromString(buf)
        except DecodeError as exc:
            raise CorruptEpisodeError(f"{name}: /camera step {t}: undecodable RawImage: {exc}") from exc
        if (image.encoding != "rgb8" or image.width != size or image.height != size
                or image.step != 3 * size or len(image.data) != pixels):
            raise CorruptEpisodeError(
                f"{name}: /camera step {t}: expected {size}x{size} rgb8 (step {3 * size}), found "
                f"{image.width}x{image.height} {image.encoding!r} step {image.step}, {len(image.data)} bytes")
        out[t] = np.frombuffer(image.data, np.uint8).reshape(size, size, 3)
    return out


def _decode_numeric(msgs: list[Message], cls, keys: tuple[str, ...], scalar: str, topic: str,
                    name: str) -> np.ndarray:
    """(T, K) float64 from one protobuf message per step."""
    k = len(keys)
    dtype = _row_dtype(k, scalar)
    if all(len(m.data) == dtype.itemsize for m in msgs):
        # Fast path: every message has encode_episode's fixed layout (all fields, in order).
        rows = np.frombuffer(b"".join(m.data for m in msgs), dtype)
        if all((rows[f"k{i}"] == _tag(i + 1, scalar)).all() for i in range(k)):
            return np.stack([rows[f"v{i}"].astype(np.float64) for i in range(k)], axis=1).reshape(-1, k)
    out = np.empty((len(msgs), k), np.float64)
    msg_obj = cls()
    for t, msg in enumerate(msgs):
        try:
            msg_obj.ParseFromString(msg.data)
        except DecodeError as exc:
            raise CorruptEpisodeError(f"{name}: {topic} step {t}: undecodable "
                                      f"{cls.DESCRIPTOR.full_name}: {exc}") from exc
        out[t] = [getattr(msg_obj, key) for key in keys]
    return out


def read_episode(source: Source, *, name: str | None = None, max_decoded: int | None = None) -> Episode:
    """Reads and fully validates an episode file (a path or the file's bytes).

    ``name`` labels the source in error messages (default: the path, or ``<bytes>``). The chunks
    are inflated only as far as the metadata's frames need (see ``decoded_limit``), and to at most
    ``max_decoded`` bytes: what a caller expecting a given episode (the service, for an upload) allows.

    Raises ``TruncatedEpisodeError`` (the file ends early), ``CorruptEpisodeError``
    (CRC mismatch, undecodable record, counts that disagree, non-finite actions or
    states, images too small for the metadata's size), ``ForeignFileError``
    (not MCAP, or MCAP without our channels/metadata) or ``EpisodeError`` (unreadable path).
    """
    scan, meta, ids, name = _examine(source, name, max_decoded)
    frames = _decode_frames(scan.messages[ids[TOPIC_CAMERA]], meta.image_size, name)
    actions = _decode_numeric(scan.messages[ids[TOPIC_ACTION]], ActionMessage, ACTION_KEYS, _ACTION_SCALAR,
                              TOPIC_ACTION, name)
    states = _decode_numeric(scan.messages[ids[TOPIC_STATE]], StateMessage, STATE_FIELDS, _STATE_SCALAR,
                             TOPIC_STATE, name)
    for topic, values in ((TOPIC_ACTION, actions), (TOPIC_STATE, states)):  # as encode_episode demands
        bad = np.flatnonzero(~np.isfinite(values).all(axis=1))
        if len(bad):
            raise CorruptEpisodeError(f"{name}: {topic} step {bad[0]}: non-finite values ({len(bad)} steps)")
    return Episode(meta=meta, frames=frames, actions=actions.astype(np.float32), states=states)


@dataclass
class EpisodeInfo:
    """What verification learns about a valid episode file."""

    meta: EpisodeMeta
    frames: int


def inspect_episode(source: Source, *, name: str | None = None) -> EpisodeInfo:
    """Validates an episode file as ``read_episode`` does; returns its metadata and length."""
    ep = read_episode(source, name=name)
    return EpisodeInfo(meta=ep.meta, frames=len(ep))


def verify_episode(source: Source, *, name: str | None = None) -> EpisodeMeta:
    """Validates an episode file as ``read_episode`` does and returns its metadata."""
    return inspect_episode(source, name=name).meta
