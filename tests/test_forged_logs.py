"""A forged log cannot make the analysis allocate without bound (analysis/limits.py):
what it claims beyond its own config record's robots and steps, or beyond its size, is
skipped unread with a LogWarning, and analysis.figures decodes no poses at all.
"""

import json
import struct
import tracemalloc
import warnings
import zlib
from pathlib import Path

import lz4.frame
import numpy as np
import pytest
import zstandard
from foxglove_schemas_protobuf.PosesInFrame_pb2 import PosesInFrame
from mcap.data_stream import RecordBuilder
from mcap.opcode import Opcode
from mcap.records import Channel, Chunk, DataEnd, Footer, Header, Metadata, Schema
from mcap.writer import MCAP0_MAGIC, CompressionType, Writer
from mcap_protobuf.schema import register_schema

from analysis.load import LogWarning, load_run
from harness.observers.log import poses_message

ROBOTS = 200
CONFIG = "agents:\n  n: 200\nsim:\n  dt: 0.02\n  t_final: 0.04\n"  # 3 steps


def forge(
    path: Path,
    config: str | None,
    repeats: int,
    huge: int,
    robots: int = ROBOTS,
    chunk: int = 1 << 20,
) -> Path:
    """A log of one poses message of ``huge`` robots, then ``repeats`` of ``robots``
    robots, with ``config`` as its config record (none when None), in chunks of
    ``chunk`` bytes (a large chunk repeats a message for a few bytes each time).
    """
    rng = np.random.default_rng(0)
    with open(path, "wb") as f:
        w = Writer(f, compression=CompressionType.ZSTD, chunk_size=chunk)
        w.start(profile="", library="forger")
        if config is not None:
            w.add_metadata("config", {"yaml": config})
        w.add_metadata("status", {"state": "completed"})
        schema = register_schema(w, PosesInFrame)  # type: ignore[arg-type]
        poses = w.register_channel("/swarm/poses", "protobuf", schema)
        metrics = w.register_channel("/metrics", "json", 0)
        heading = np.vstack([np.ones(robots), np.zeros(robots)])
        one = poses_message(0.0, rng.random((2, robots)), heading)
        for k in range(3):
            w.add_message(metrics, k * 20_000_000, json.dumps({"t": k * 0.02}).encode(), 0)
        many = poses_message(0.0, np.zeros((2, huge)), np.vstack([np.ones(huge), np.zeros(huge)]))
        w.add_message(poses, 0, many, 0)
        for k in range(1, repeats + 1):
            w.add_message(poses, k * 1000, one, k * 1000)
        w.finish()
    return path


MILLIONS = "agents:\n  n: 8000000\nsim:\n  dt: 0.02\n  t_final: 0.04\n"  # a lie: 8 M robots


def bomb(
    path: Path, config: str, robots: int, declared: int | None = None, compression: str = "zstd"
) -> Path:
    """A log whose one chunk holds one poses message of ``robots`` robots, compressed
    (``zstd`` or ``lz4``) as it streams (never whole in memory): a few kB of file for 69
    bytes per robot. The chunk's header declares ``declared`` uncompressed bytes (default:
    the truth; a smaller one is a lie that the zstd frame's own content size then tells,
    and that the LZ4 frame, written without its size, does not).
    """
    head = poses_message(0.0, np.zeros((2, 0)), np.zeros((2, 0)))
    pose = poses_message(0.0, np.zeros((2, 1)), np.array([[1.0], [0.0]]))[len(head) :]
    data_size = len(head) + robots * len(pose)
    size = 9 + 22 + data_size  # the message record: opcode, length, its fields, data
    record = struct.pack("<BQHIQQ", Opcode.MESSAGE, 22 + data_size, 1, 0, 0, 0) + head
    piece = pose * 16384
    write_size = declared is not None
    parts: list[bytes] = []
    if compression == "lz4":
        packer = lz4.frame.LZ4FrameCompressor()
        parts.append(packer.begin())  # no source size: the frame does not say
    else:
        packer = zstandard.ZstdCompressor(write_content_size=write_size).compressobj(
            size=size if write_size else -1
        )
    parts.append(packer.compress(record))
    crc = zlib.crc32(record)
    left = robots
    while left:
        n = min(left, 16384)
        block = piece if n == 16384 else pose * n
        parts.append(packer.compress(block))
        crc = zlib.crc32(block, crc)
        left -= n
    parts.append(packer.flush())
    b = RecordBuilder()
    Header(profile="", library="forger").write(b)
    Metadata(name="config", metadata={"yaml": config}).write(b)
    Metadata(name="status", metadata={"state": "completed"}).write(b)
    Schema(id=1, name="foxglove.PosesInFrame", encoding="protobuf", data=b"").write(b)
    Channel(
        id=1, topic="/swarm/poses", message_encoding="protobuf", metadata={}, schema_id=1
    ).write(b)
    Chunk(
        compression=compression,
        data=b"".join(parts),
        message_start_time=0,
        message_end_time=0,
        uncompressed_crc=crc,
        uncompressed_size=size if declared is None else declared,
    ).write(b)
    DataEnd(data_section_crc=0).write(b)
    Footer(summary_start=0, summary_offset_start=0, summary_crc=0).write(b)
    path.write_bytes(MCAP0_MAGIC + b.end() + MCAP0_MAGIC)
    return path


@pytest.mark.parametrize("declared", [None, 4096], ids=["declared", "understated"])
@pytest.mark.parametrize("compression", ["zstd", "lz4"])
def test_a_config_record_claiming_millions_of_robots_cannot_make_a_small_log_cost_gigabytes(
    tmp_path, declared, compression
):
    path = bomb(tmp_path / "run.mcap", MILLIONS, 8_000_000, declared, compression)
    assert path.stat().st_size < 3_000_000  # 552 MB of poses claimed
    tracemalloc.start()
    try:
        with pytest.warns(LogWarning, match="decompressed bytes per byte|does not decompress"):
            run = load_run(path)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert run.poses == [] and run.recovery is not None
    if declared is None:  # the truth, beyond what the file's size allows: not read
        assert "not read" in run.recovery, run.recovery
    elif compression == "lz4":  # a lie found by decompressing one byte past it
        assert "does not decompress to the 4096 bytes" in run.recovery, run.recovery
    assert peak < 20e6, f"{peak / 1e6:.0f} MB to read a log of {path.stat().st_size} bytes"


def test_an_honest_lz4_chunk_is_read_whole(tmp_path):
    path = bomb(tmp_path / "run.mcap", "agents:\n  n: 300\n", 300, compression="lz4")
    run = load_run(path)
    assert len(run.poses) == 1 and run.poses[0].shape[0] == 300, run.recovery


def test_a_config_record_claiming_millions_of_robots_does_not_lift_the_points_per_byte(
    tmp_path,
):
    path = forge(tmp_path / "run.mcap", MILLIONS, repeats=3, huge=200_000)
    size = path.stat().st_size
    assert 200_000 > 4 * size  # more poses than 4 per byte of the file, fewer than claimed
    with pytest.warns(LogWarning, match="points per byte"):
        run = load_run(path)
    assert sum(p.shape[0] for p in run.poses) <= 4 * size
    assert all(p.shape == (ROBOTS, 3) for p in run.poses)


def test_a_log_claiming_more_poses_than_its_robots_and_steps_is_read_within_them(tmp_path):
    path = forge(tmp_path / "run.mcap", CONFIG, repeats=1000, huge=100 * ROBOTS)
    assert path.stat().st_size < 200_000  # 220 000 poses claimed
    tracemalloc.start()
    try:
        with pytest.warns(LogWarning, match="more than the log's config and size allow"):
            run = load_run(path)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert len(run.poses) <= 3 + 2 and all(p.shape == (ROBOTS, 3) for p in run.poses)
    assert "messages beyond its 5 steps" in run.recovery
    assert "too large for 200 robots" in run.recovery  # the huge one, never parsed
    assert peak < 20e6, f"{peak / 1e6:.0f} MB to read a log of {path.stat().st_size} bytes"
    assert run.metrics["t"].size == 3  # the rest of the log is read


def test_a_log_without_a_config_record_is_bounded_by_its_size(tmp_path):
    path = forge(tmp_path / "run.mcap", None, repeats=100, huge=ROBOTS, robots=5000, chunk=1 << 27)
    size = path.stat().st_size
    assert 100 * 5000 > 4 * size  # more points than the size allows, in one chunk of 35 MB
    with pytest.warns(LogWarning, match="points per byte"):
        run = load_run(path)
    assert sum(p.shape[0] for p in run.poses) <= 4 * size


def test_a_log_within_its_config_is_read_whole_without_a_warning(tmp_path):
    path = forge(tmp_path / "run.mcap", CONFIG, repeats=2, huge=ROBOTS)
    with warnings.catch_warnings():
        warnings.simplefilter("error", LogWarning)
        run = load_run(path)
    assert len(run.poses) == 3 and run.recovery is None, run.recovery


def test_figures_decode_no_poses(tmp_path, monkeypatch):
    from analysis import figures, load
    from harness import api

    log = api.run(["+experiment=smoke", "plant=unicycles", "sim.t_final=0.2"], tmp_path / "r")
    assert len(log.poses) > 0
    parsed = []

    class Counting:
        @staticmethod
        def FromString(data):
            parsed.append(len(data))
            return PosesInFrame.FromString(data)

    monkeypatch.setattr(load, "PosesInFrame", Counting)
    assert figures.main([str(tmp_path / "r"), "--out", str(tmp_path / "f"), "--no-gif"]) == 0
    assert parsed == []
