"""Episodes on disk: MCAP round trip, what other tools see, and refusal of bad files."""

from __future__ import annotations

from collections.abc import Callable

import dataclasses
import io
import json
import re
import struct
import tracemalloc
import os
import uuid

import lz4.frame
import numpy as np
import pytest
import zstandard
from foxglove_schemas_protobuf.RawImage_pb2 import RawImage
from mcap.reader import make_reader
from mcap.opcode import Opcode
from mcap.records import Chunk
from mcap.writer import CompressionType, Writer
from mcap_protobuf.decoder import DecoderFactory

from storage import episode_reader, episodes, files
from storage.catalog import Catalog
from storage.errors import (
    CorruptEpisodeError,
    EpisodeError,
    ForeignFileError,
    OversizedEpisodeError,
    StorageError,
    TruncatedEpisodeError,
)
from storage.records import STATE_DIM, STATE_FIELDS, Episode, EpisodeMeta, trainable_size


def make_episode(rng: np.random.Generator, steps: int = 6, size: int = 16, shape: str = "T",
                 created: str = "2026-11-21T05:00:00+00:00", **meta_fields) -> Episode:
    """A synthetic episode (storage must not depend on the simulator)."""
    meta = EpisodeMeta(
        episode_id=uuid.UUID(bytes=rng.bytes(16)).hex, task="push", shape=shape,
        physics={"mass": float(rng.uniform(0.2, 5)), "friction": 0.6, "ground_friction": 1.0},
        seed=int(rng.integers(2**31)), policy="push", policy_params={"side": "left", "noise": 0.1},
        start_state={"shape": shape, "agent": [1.5, 2.25]}, image_size=size, created=created,
        software_version="0.1.0", **meta_fields)
    frames = rng.integers(0, 256, (steps, size, size, 3), dtype=np.uint8)
    actions = rng.uniform(0, 512, (steps, 2)).astype(np.float32)
    states = rng.normal(0, 100, (steps, STATE_DIM))
    states[:, -1] = rng.integers(0, 2, steps)
    if steps:
        states[0, 0] = -0.0
    return Episode(meta, frames, actions, states)


def assert_same(a: Episode, b: Episode) -> None:
    assert a.meta == b.meta
    assert a.frames.dtype == b.frames.dtype == np.uint8 and np.array_equal(a.frames, b.frames)
    assert a.actions.dtype == b.actions.dtype == np.float32 and np.array_equal(a.actions, b.actions)
    assert a.states.dtype == b.states.dtype == np.float64
    assert a.states.tobytes() == b.states.tobytes()  # bit-exact, -0.0 included


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(7)


@pytest.fixture
def ep(rng) -> Episode:
    return make_episode(rng)


@pytest.fixture
def data(ep) -> bytes:
    return episodes.encode_episode(ep)


# --- round trip --------------------------------------------------------------------------------


def test_round_trip_bytes_and_path(ep, data, tmp_path):
    assert_same(episode_reader.read_episode(data), ep)
    path = tmp_path / "a" / "ep.mcap"
    sha = episodes.write_episode(path, ep)
    assert sha == files.sha256_hex(path.read_bytes()) == files.sha256_hex(data)
    assert_same(episode_reader.read_episode(path), ep)
    assert_same(episode_reader.read_episode(str(path)), ep)
    assert episode_reader.verify_episode(path) == ep.meta


def test_same_episode_same_bytes(ep, data):
    assert episodes.encode_episode(ep) == data


@pytest.mark.parametrize("steps,size", [(1, 4), (30, 16)])
def test_round_trip_sizes(rng, steps, size):
    ep = make_episode(rng, steps=steps, size=size, request_id="r1", worker_id="w1", model_version="m3")
    assert_same(episode_reader.read_episode(episodes.encode_episode(ep)), ep)


def test_multi_chunk_round_trip(rng, monkeypatch):
    monkeypatch.setattr(episodes, "CHUNK_SIZE", 1000)  # a chunk per message or so
    ep = make_episode(rng, steps=12, size=12)
    data = episodes.encode_episode(ep)
    summary = make_reader(io.BytesIO(data)).get_summary()
    assert len(summary.chunk_indexes) > 5
    assert_same(episode_reader.read_episode(data), ep)


def test_time_stamps_follow_control_hz(rng):
    ep = make_episode(rng, steps=4)
    ep.meta.control_hz = 20.0
    reader = make_reader(io.BytesIO(episodes.encode_episode(ep)))
    times = [m.log_time for _, c, m in reader.iter_messages(topics=["/camera"])]
    assert times == [0, 50_000_000, 100_000_000, 150_000_000]


# --- what other MCAP tools see -----------------------------------------------------------------


def test_mcap_reader_sees_foxglove_raw_image(ep, data):
    reader = make_reader(io.BytesIO(data), validate_crcs=True, decoder_factories=[DecoderFactory()])
    summary = reader.get_summary()
    topics = {c.topic: summary.schemas[c.schema_id] for c in summary.channels.values()}
    assert topics["/camera"].name == "foxglove.RawImage" and topics["/camera"].encoding == "protobuf"
    assert topics["/action"].name == "activecollect.Action"
    assert topics["/state"].name == "activecollect.State"
    assert summary.statistics.message_count == 3 * len(ep)
    assert {c.message_encoding for c in summary.channels.values()} == {"protobuf"}
    assert all(ci.compression in ("lz4", "zstd") for ci in summary.chunk_indexes)

    decoded = {"/camera": [], "/action": [], "/state": []}
    for _schema, channel, message, obj in reader.iter_decoded_messages():
        decoded[channel.topic].append((message.log_time, obj))
    size = ep.meta.image_size
    for t, (_, img) in enumerate(decoded["/camera"]):
        assert (img.width, img.height, img.encoding, img.step) == (size, size, "rgb8", 3 * size)
        assert img.timestamp.ToNanoseconds() == t * 100_000_000
        assert np.array_equal(np.frombuffer(img.data, np.uint8).reshape(size, size, 3), ep.frames[t])
    for t, (_, st) in enumerate(decoded["/state"]):
        assert [getattr(st, f) for f in STATE_FIELDS] == ep.states[t].tolist()
    assert [(a.x, a.y) for _, a in decoded["/action"]] == [tuple(r) for r in ep.actions.tolist()]

    meta = {m.name: m.metadata for m in reader.iter_metadata()}
    assert meta["episode"]["episode_id"] == ep.meta.episode_id
    assert meta["episode"]["frames"] == str(len(ep))
    assert EpisodeMeta.from_json(meta["episode"]["json"]) == ep.meta


def test_camera_message_parses_like_protobufs_own(ep, data):
    reader = make_reader(io.BytesIO(data))
    _, _, msg = next(iter(reader.iter_messages(topics=["/camera"])))
    ours = RawImage.FromString(msg.data)
    size = ep.meta.image_size
    theirs = RawImage(frame_id="camera", width=size, height=size, encoding="rgb8", step=3 * size,
                      data=ep.frames[0].tobytes())
    theirs.timestamp.FromNanoseconds(0)
    assert ours == theirs


# --- refusing bad files ------------------------------------------------------------------------


@pytest.mark.parametrize("keep", [0, 3, 8, 20, 0.5, -1, -8, -20])
def test_truncated_file_refused(data, keep):
    cut = int(len(data) * keep) if isinstance(keep, float) else (keep if keep >= 0 else len(data) + keep)
    with pytest.raises(TruncatedEpisodeError, match="bytes"):
        episode_reader.read_episode(data[:cut])


def test_truncated_file_on_disk_names_the_file(data, tmp_path):
    path = tmp_path / "cut.mcap"
    path.write_bytes(data[: len(data) // 3])
    with pytest.raises(TruncatedEpisodeError, match="cut.mcap.*without an MCAP footer"):
        episode_reader.verify_episode(path)


def _flip(data: bytes, pos: int, bit: int = 0) -> bytes:
    out = bytearray(data)
    out[pos] ^= 1 << bit
    return bytes(out)


def test_every_flipped_bit_refused_as_corrupt(data):
    rng = np.random.default_rng(0)
    positions = sorted(set(range(0, 40)) | set(range(len(data) - 60, len(data)))
                       | set(rng.integers(0, len(data), 150).tolist()))
    for pos in positions:
        bad = _flip(data, pos, bit=pos % 8)
        with pytest.raises(CorruptEpisodeError) as info:
            episode_reader.read_episode(bad)
        assert str(info.value).startswith("<bytes>: "), (pos, info.value)


def test_bit_flip_in_pixels_names_the_crc(rng, tmp_path):
    # Big, incompressible frames so the flipped byte lands inside a chunk's compressed pixels.
    ep = make_episode(rng, steps=3, size=32)
    path = tmp_path / "flip.mcap"
    episodes.write_episode(path, ep)
    data = path.read_bytes()
    path.write_bytes(_flip(data, len(data) // 2, 3))
    with pytest.raises(CorruptEpisodeError, match="flip.mcap: data section CRC mismatch"):
        episode_reader.read_episode(path)


@pytest.mark.parametrize("blob", [
    b"hello, this is a text file, not an episode\n" * 5,
    bytes(np.random.default_rng(3).integers(0, 256, 4096, dtype=np.uint8)),
    b"\x00\x01",
])
def test_foreign_bytes_refused(blob):
    with pytest.raises(ForeignFileError, match="not an MCAP file"):
        episode_reader.read_episode(blob)


def _plain_mcap(topic: str = "/foo", with_meta: bool = False) -> bytes:
    buf = io.BytesIO()
    w = Writer(buf)
    w.start()
    sid = w.register_schema("Foo", "jsonschema", b'{"type":"object"}')
    cid = w.register_channel(topic, "json", sid)
    for t in range(3):
        w.add_message(cid, t, b'{"a":1}', t, t)
    if with_meta:
        w.add_metadata("episode", {"format": episodes.FORMAT, "frames": "3", "json": "{}"})
    w.finish()
    return buf.getvalue()


def test_valid_mcap_without_our_channels_refused():
    with pytest.raises(ForeignFileError, match="not an activecollect episode"):
        episode_reader.read_episode(_plain_mcap())


def test_valid_mcap_with_our_metadata_but_no_channels_refused(ep):
    buf = io.BytesIO()
    w = Writer(buf)
    w.start()
    w.add_metadata("episode", episodes._metadata_record(ep))
    w.finish()
    with pytest.raises(ForeignFileError, match="no /camera channel"):
        episode_reader.read_episode(buf.getvalue())


def test_camera_with_other_schema_refused(ep):
    buf = io.BytesIO()
    w = Writer(buf)
    w.start()
    sid = w.register_schema("foxglove.CompressedImage", "protobuf", b"")
    w.register_channel("/camera", "protobuf", sid)
    w.add_metadata("episode", episodes._metadata_record(ep))
    w.finish()
    with pytest.raises(ForeignFileError, match="expected 'protobuf' 'foxglove.RawImage'"):
        episode_reader.read_episode(buf.getvalue())


def _episode_like_mcap(ep: Episode, skip: tuple[str, int] | None = None,
                       compression: CompressionType = CompressionType.ZSTD, pad: int = 0,
                       times: Callable[[int], int] = lambda t: t, crcs: bool = True) -> bytes:
    """Our layout written by hand with mcap's Writer, optionally leaving out one message or adding a
    ``pad``-byte message of zeros (which compresses to almost nothing) on a channel of its own."""
    buf = io.BytesIO()
    w = Writer(buf, compression=compression, enable_crcs=crcs)
    w.start()
    if pad:
        w.add_message(w.register_channel("/pad", "", 0), 0, bytes(pad), 0, 0)
    image = w.register_schema("foxglove.RawImage", "protobuf", episodes._IMAGE_SCHEMA_DATA)
    action = w.register_schema("activecollect.Action", "protobuf", episodes._NUMERIC_SCHEMA_DATA)
    state = w.register_schema("activecollect.State", "protobuf", episodes._NUMERIC_SCHEMA_DATA)
    channels = {"/camera": w.register_channel("/camera", "protobuf", image),
                "/action": w.register_channel("/action", "protobuf", action),
                "/state": w.register_channel("/state", "protobuf", state)}
    w.add_metadata("episode", episodes._metadata_record(ep))
    size = ep.meta.image_size
    for t in range(len(ep)):
        img = RawImage(width=size, height=size, encoding="rgb8", step=3 * size, data=ep.frames[t].tobytes())
        payloads = {"/camera": img.SerializeToString(),
                    "/action": episodes.ActionMessage(x=ep.actions[t, 0], y=ep.actions[t, 1]).SerializeToString(),
                    "/state": episodes.StateMessage(**dict(zip(STATE_FIELDS, ep.states[t]))).SerializeToString()}
        for topic, payload in payloads.items():
            if skip != (topic, t):
                w.add_message(channels[topic], times(t), payload, times(t), t)
    w.finish()
    return buf.getvalue()


@pytest.mark.parametrize("compression", list(CompressionType))
def test_canonical_protobuf_encoding_reads_back(ep, compression):
    """Another writer's canonical protobuf (zeros omitted, fields in order) reads the same."""
    assert_same(episode_reader.read_episode(_episode_like_mcap(ep, compression=compression)), ep)


@pytest.mark.parametrize("compression", [CompressionType.ZSTD, CompressionType.LZ4])
def test_a_chunk_that_inflates_past_what_the_frames_need_is_refused_before_inflating(ep, compression):
    data = _episode_like_mcap(ep, compression=compression, pad=32 << 20)
    assert len(data) < 1 << 20  # 32 MiB of content in a small file
    tracemalloc.start()
    try:
        with pytest.raises(OversizedEpisodeError, match=r"inflates to 335\d+ bytes; the episode's frames need at most"):
            episode_reader.read_episode(data)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 4 * len(data) + (1 << 20)
    with pytest.raises(OversizedEpisodeError, match="frames need at most 1000 more"):
        episode_reader.read_episode(_episode_like_mcap(ep), max_decoded=1000)  # what an upload's caller allows


@pytest.mark.parametrize("compression", ["zstd", "lz4"])
def test_a_chunk_holding_more_than_it_declares_is_not_inflated_past_it(compression):
    body = bytes(8 << 20)
    packed = zstandard.compress(body) if compression == "zstd" else lz4.frame.compress(body)
    chunk = Chunk(compression=compression, data=packed, message_start_time=0, message_end_time=0,
                  uncompressed_crc=0, uncompressed_size=100)
    with pytest.raises(CorruptEpisodeError, match="declares 100 bytes of content and holds more"):
        episode_reader._inflate(chunk, "x")
    with pytest.raises(ForeignFileError, match="compression 'bz2'"):
        episode_reader._inflate(Chunk(compression="bz2", data=b"", message_start_time=0, message_end_time=0,
                                uncompressed_crc=0, uncompressed_size=0), "x")


def test_missing_messages_refused_not_read_partially(ep):
    """A well-formed file whose /state channel lacks a step is refused, not returned short."""
    data = _episode_like_mcap(ep, skip=("/state", len(ep) - 1))
    with pytest.raises(CorruptEpisodeError, match=r"/state holds 5 messages, summary says 5, metadata says 6"):
        episode_reader.read_episode(data)


def test_errors_are_storage_errors_not_raw(ep, data):
    """Whatever is wrong, callers only ever see StorageError subclasses, and never an episode other than the one
    written (16 random bytes anywhere in the file)."""
    rng = np.random.default_rng(1)
    refused = 0
    for _ in range(40):
        bad = bytearray(data)
        start = int(rng.integers(0, len(data)))
        bad[start:start + 16] = rng.integers(0, 256, len(bad[start:start + 16]), dtype=np.uint8).tobytes()
        try:
            got = episode_reader.read_episode(bytes(bad))
        except StorageError:
            refused += 1
        else:
            assert_same(got, ep)
    assert refused > 0


def test_missing_path_is_episode_error(tmp_path):
    with pytest.raises(EpisodeError, match="no such file"):
        episode_reader.read_episode(tmp_path / "nope.mcap")


# --- writing safely ----------------------------------------------------------------------------


def test_write_failure_leaves_no_file_and_no_temp(tmp_path):
    path = tmp_path / "ep.mcap"
    with pytest.raises(TypeError):
        files.write_bytes_atomic(path, ["not", "bytes"])  # fails after the temp file exists
    assert os.listdir(tmp_path) == []


def test_failed_overwrite_keeps_old_file(ep, data, tmp_path):
    path = tmp_path / "ep.mcap"
    episodes.write_episode(path, ep)
    with pytest.raises(TypeError):
        files.write_bytes_atomic(path, object())
    assert path.read_bytes() == data
    assert os.listdir(tmp_path) == ["ep.mcap"]


def test_unwritable_episode_refused_before_any_file(rng, tmp_path):
    ep = make_episode(rng)
    ep.states[2, 4] = np.nan
    with pytest.raises(EpisodeError, match="states must be finite"):
        episodes.write_episode(tmp_path / "x.mcap", ep)
    ep = make_episode(rng, size=8)
    ep.meta.image_size = 64
    with pytest.raises(EpisodeError, match="frames are 8x8, meta.image_size says 64"):
        episodes.encode_episode(ep)
    with pytest.raises(EpisodeError, match="has no steps"):
        episodes.encode_episode(make_episode(rng, steps=0))
    ep = make_episode(rng)
    ep.meta.seed = "7"
    with pytest.raises(EpisodeError, match="field seed is str '7', expected int"):
        episodes.encode_episode(ep)
    assert os.listdir(tmp_path) == []


def _encode_unchecked(ep: Episode, monkeypatch) -> bytes:
    """The bytes a writer that skips our checks would produce (all CRCs valid)."""
    with monkeypatch.context() as m:
        m.setattr(episodes, "_check_writable", lambda ep: None)
        return episodes.encode_episode(ep)


@pytest.mark.parametrize("size, error, words", [
    (1024, CorruptEpisodeError, "cannot hold"),
    (10**6, OversizedEpisodeError, "no episode has frames larger than 1024px"),  # (refused before inflating)
    (2**40, OversizedEpisodeError, "no episode has frames larger than 1024px"),
])
def test_a_metadata_image_size_the_images_cannot_hold_is_refused_before_allocating(rng, monkeypatch, size, error,
                                                                                   words):
    ep = make_episode(rng)
    ep.meta.image_size = size
    with pytest.raises(error, match=words):
        episode_reader.read_episode(_encode_unchecked(ep, monkeypatch))


def test_non_finite_actions_or_states_are_refused_on_read_as_on_write(rng, monkeypatch, tmp_path):
    ep = make_episode(rng)
    ep.states[1, 0] = float("nan")
    with pytest.raises(EpisodeError, match="finite"):
        episodes.encode_episode(ep)
    data = _encode_unchecked(ep, monkeypatch)
    with pytest.raises(CorruptEpisodeError, match="/state step 1: non-finite"):
        episode_reader.read_episode(data)
    cat = Catalog(tmp_path)
    with pytest.raises(CorruptEpisodeError):
        cat.ingest_bytes(data)
    assert cat.count() == 0


def test_a_creation_time_past_the_last_utc_day_is_still_ingested(rng, tmp_path):
    ep = make_episode(rng, created="9999-12-31T23:00:00-05:00")
    result = Catalog(tmp_path).ingest_bytes(episodes.encode_episode(ep))
    assert result.path.is_file()


@pytest.mark.parametrize("change, words", [
    ({"physics": {"mass": float("nan")}}, "holds NaN"),
    ({"physics": {"mass": float("inf")}}, "holds Infinity"),
    ({"model_version": "v" * 1000}, "model_version has 1000 characters, expected at most 256"),
    ({"policy_params": {"blob": "x" * 200_000}}, "expected at most 65536 bytes"),
])
def test_metadata_the_catalog_cannot_hold_is_refused_on_write_and_on_read(rng, monkeypatch, tmp_path, change,
                                                                          words):
    ep = make_episode(rng)
    ep.meta = dataclasses.replace(ep.meta, **change)
    with pytest.raises(EpisodeError):
        episodes.encode_episode(ep)
    with monkeypatch.context() as m:  # what another writer could make: Python's json writes NaN by default
        m.setattr(EpisodeMeta, "to_json", lambda self: json.dumps(dataclasses.asdict(self), sort_keys=True))
        data = _encode_unchecked(ep, monkeypatch)
    cat = Catalog(tmp_path)
    with pytest.raises(CorruptEpisodeError, match=words):
        cat.ingest_bytes(data)
    assert cat.count() == 0
    # a NaN in the first row's JSON once made every later ingest fail ("malformed JSON")
    assert not cat.ingest_bytes(episodes.encode_episode(make_episode(rng))).duplicate


@pytest.mark.parametrize("times, words", [
    (lambda t: 100 - t, "/camera step 1 is logged at 99 ns, not after step 0 (100 ns)"),
    (lambda t: 0, "/camera step 1 is logged at 0 ns, not after step 0 (0 ns)"),
])
def test_steps_logged_out_of_time_order_are_refused(ep, times, words):
    with pytest.raises(CorruptEpisodeError, match=re.escape(words)):
        episode_reader.read_episode(_episode_like_mcap(ep, times=times))


def test_a_chunk_without_a_crc_is_refused(ep):
    with pytest.raises(CorruptEpisodeError, match="has no CRC"):
        episode_reader.read_episode(_episode_like_mcap(ep, crcs=False))


def test_a_chunk_record_longer_than_its_index_says_is_refused(ep):
    data = bytearray(_episode_like_mcap(ep))  # no data-section CRC: only the chunk's own fields guard it
    at = make_reader(io.BytesIO(bytes(data))).get_summary().chunk_indexes[0].chunk_start_offset
    assert data[at] == Opcode.CHUNK
    struct.pack_into("<Q", data, at + 1, 1 << 62)
    with pytest.raises(CorruptEpisodeError, match=r"says it is 4611686018427387904 bytes long, its index"):
        episode_reader.read_episode(bytes(data))


def test_a_model_trains_on_multiples_of_8_from_16_to_1024() -> None:
    assert [s for s in range(-8, 2048) if trainable_size(s)] == list(range(16, 1025, 8))
    assert not any(trainable_size(v) for v in (True, 16.0, "16", None))
