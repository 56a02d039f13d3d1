"""Reading an episode file back (``read_episode``), and validating it (``inspect_episode``,
``verify_episode``).

Validation comes before decoding: the envelope first (the magic, the footer, the summary's and the
data section's CRCs: ``_check_envelope``), then the summary, the ``episode`` metadata and our three
channels (``_scan``), each chunk against its CRC, inflated no further than the metadata's frames need
(``decoded_limit``; ``_read_chunks``), and the message counts and order (``_check_counts``); only then
are the messages decoded. Each refusal is an ``EpisodeError`` whose message starts with the source's name
(``read_episode`` lists them). The format, and the writer these files come from, are ``storage.episodes``'s.

Cost at 96x96 on the 2-core dev box (CPU time, 100-step push episodes): reading ~18 us per frame.
The reader recognises the exact bytes ``storage.episodes.encode_episode`` makes and skips protobuf
parsing for them; any other valid encoding of the same schemas (another writer's) is parsed with
protobuf.
"""

from __future__ import annotations

import io
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
from google.protobuf.message import DecodeError
from google.protobuf.unknown_fields import UnknownFieldSet
from mcap.exceptions import McapError
from mcap.opcode import Opcode
from mcap.reader import FOOTER_SIZE, SeekingReader
from mcap.data_stream import ReadDataStream
from mcap.records import Channel, Chunk, Message, Schema, Statistics
from mcap.stream_reader import CRCValidationError

from storage.episodes import (ACTION_KEYS, ACTION_SCALAR, ACTION_SCHEMA, FORMAT, IMAGE_SCHEMA, METADATA_NAME,
                              STATE_SCALAR, STATE_SCHEMA, TOPIC_ACTION, TOPIC_CAMERA, TOPIC_STATE, ActionMessage,
                              StateMessage, check_meta, image_prefix, row_dtype, tag, timestamp_field)
from storage.errors import (CorruptEpisodeError, EpisodeError, ForeignFileError, FrameSizeError, OversizedEpisodeError,
                            StorageError, TruncatedEpisodeError)
from storage.records import MAX_FRAME_SIZE, STATE_FIELDS, Episode, EpisodeMeta

Source = Union[str, os.PathLike, bytes, bytearray, memoryview]

MAGIC = b"\x89MCAP0\r\n"
_DATA_END_SIZE = 1 + 8 + 4
_TRAILER_SIZE = FOOTER_SIZE + len(MAGIC)


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


#: The most any file's chunks may inflate to, whatever its metadata claims: the largest episode anything records
#: (1,000 steps, the wire's most, of ``MAX_FRAME_SIZE`` frames). A small file whose metadata claims a vast episode
#: costs no more memory than the largest real one.
MAX_DECODED_BYTES = decoded_limit(1000, MAX_FRAME_SIZE)


def _scan(data: bytes, name: str, max_decoded: int | None = None,
          frame_size: int | None = None) -> tuple[_Scan, EpisodeMeta, int, dict[str, int]]:
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
        if meta.image_size > MAX_FRAME_SIZE:  # no catalog takes it: refused before its chunks are inflated
            raise OversizedEpisodeError(f"{name}: episode metadata says {meta.image_size}px frames; no episode has "
                                        f"frames larger than {MAX_FRAME_SIZE}px")
        if frame_size and meta.image_size != frame_size:  # (not inflated to the size it says, either)
            raise FrameSizeError(f"{name}: {meta.image_size}px frames, expected {frame_size}px", meta.image_size,
                                 frame_size)
        ids = {TOPIC_CAMERA: _channel(scan, TOPIC_CAMERA, IMAGE_SCHEMA, "protobuf", name),
               TOPIC_ACTION: _channel(scan, TOPIC_ACTION, ACTION_SCHEMA, "protobuf", name),
               TOPIC_STATE: _channel(scan, TOPIC_STATE, STATE_SCHEMA, "protobuf", name)}
        budget = min(decoded_limit(frames, meta.image_size), MAX_DECODED_BYTES)
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
    check_meta(meta, frames, name)
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


def _examine(source: Source, name: str | None, max_decoded: int | None = None,
             frame_size: int | None = None) -> tuple[_Scan, EpisodeMeta, dict[str, int], str]:
    data, name = _load(source, name)
    _check_envelope(data, name)
    scan, meta, frames, ids = _scan(data, name, max_decoded, frame_size)
    _check_counts(scan, ids, frames, name)
    return scan, meta, ids, name


def _decode_frames(msgs: list[Message], size: int, name: str) -> np.ndarray:
    pixels = 3 * size * size
    short = next((t for t, m in enumerate(msgs) if len(m.data) < pixels), None)
    if short is not None:  # checked before allocating: a hostile image_size must not cost memory
        raise CorruptEpisodeError(f"{name}: /camera step {short}: {len(msgs[short].data)} bytes cannot hold "
                                  f"a {size}x{size} rgb8 image (metadata image_size {size})")
    out = np.empty((len(msgs), size, size, 3), np.uint8)
    prefix = image_prefix(size, size)
    image = RawImage()
    for t, msg in enumerate(msgs):
        buf = msg.data
        head = len(buf) - pixels
        # Fast path: exactly the bytes encode_episode writes for this step (no parse, one copy).
        if head >= len(prefix) and buf[head - len(prefix):head] == prefix \
                and buf[:head - len(prefix)] == timestamp_field(msg.log_time):
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
    dtype = row_dtype(k, scalar)
    if all(len(m.data) == dtype.itemsize for m in msgs):
        # Fast path: every message has encode_episode's fixed layout (all fields, in order).
        rows = np.frombuffer(b"".join(m.data for m in msgs), dtype)
        if all((rows[f"k{i}"] == tag(i + 1, scalar)).all() for i in range(k)):
            return np.stack([rows[f"v{i}"].astype(np.float64) for i in range(k)], axis=1).reshape(-1, k)
    out = np.empty((len(msgs), k), np.float64)
    msg_obj = cls()
    for t, msg in enumerate(msgs):
        try:
            msg_obj.ParseFromString(msg.data)
        except DecodeError as exc:
            raise CorruptEpisodeError(f"{name}: {topic} step {t}: undecodable "
                                      f"{cls.DESCRIPTOR.full_name}: {exc}") from exc
        unknown = [(f.field_number, f.wire_type) for f in UnknownFieldSet(msg_obj)]
        if unknown:  # protobuf would drop them and read zeros: another length, or doubles where floats belong
            raise CorruptEpisodeError(
                f"{name}: {topic} step {t}: field {unknown[0][0]} (wire type {unknown[0][1]}) is not one of "
                f"{cls.DESCRIPTOR.full_name}'s {k} fields ({', '.join(keys[:3])}{', ...' if k > 3 else ''}: "
                f"{'float' if scalar == ACTION_SCALAR else 'double'} each)")
        out[t] = [getattr(msg_obj, key) for key in keys]
    return out


def read_episode(source: Source, *, name: str | None = None, max_decoded: int | None = None,
                 frame_size: int | None = None) -> Episode:
    """Reads and fully validates an episode file (a path or the file's bytes).

    ``name`` labels the source in error messages (default: the path, or ``<bytes>``). The chunks
    are inflated only as far as the metadata's frames need (see ``decoded_limit``), and to at most
    ``max_decoded`` bytes: what a caller expecting a given episode (the service, for an upload) allows.
    ``frame_size``: the only frame size taken (None or 0: any); another is ``FrameSizeError``, from the metadata.

    Raises ``TruncatedEpisodeError`` (the file ends early), ``CorruptEpisodeError``
    (CRC mismatch, undecodable record, counts that disagree, non-finite actions or
    states, actions or states with fields their schema lacks, images too small for the
    metadata's size), ``OversizedEpisodeError`` (frames larger than ``MAX_FRAME_SIZE``, chunks
    inflating past what the frames need), ``ForeignFileError``
    (not MCAP, or MCAP without our channels/metadata), ``FrameSizeError`` (not ``frame_size``) or ``EpisodeError``
    (unreadable path).
    """
    scan, meta, ids, name = _examine(source, name, max_decoded, frame_size)
    frames = _decode_frames(scan.messages[ids[TOPIC_CAMERA]], meta.image_size, name)
    actions = _decode_numeric(scan.messages[ids[TOPIC_ACTION]], ActionMessage, ACTION_KEYS, ACTION_SCALAR,
                              TOPIC_ACTION, name)
    states = _decode_numeric(scan.messages[ids[TOPIC_STATE]], StateMessage, STATE_FIELDS, STATE_SCALAR,
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
