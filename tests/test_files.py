"""The safe reader (harness/files.py) against files that would hang or flood a plain
``open().read()``: a FIFO, a device behind a symbolic link, a file over the limit, bytes
that do not decode."""

from __future__ import annotations

import os
import threading

import pytest

from harness.files import UnreadableFile, read_bytes, read_text


def test_a_regular_file_is_read(tmp_path):
    path = tmp_path / "a.json"
    path.write_text('{"x": 1}')
    assert read_text(path, 100) == '{"x": 1}'
    assert read_bytes(path, 8) == b'{"x": 1}'


def test_a_fifo_is_refused_at_once(tmp_path):
    path = tmp_path / "entry.json"
    os.mkfifo(path)
    done = threading.Event()
    errors = []

    def read():
        try:
            read_bytes(path, 100)
        except UnreadableFile as err:
            errors.append(str(err))
        done.set()

    threading.Thread(target=read, daemon=True).start()
    assert done.wait(5.0), "the read of a FIFO blocked"
    assert errors and "FIFO" in errors[0] and "\n" not in errors[0]


def test_a_device_behind_a_link_is_refused(tmp_path):
    path = tmp_path / "entry.json"
    path.symlink_to("/dev/zero")
    with pytest.raises(UnreadableFile, match="character device"):
        read_bytes(path, 1 << 30)


def test_a_file_over_the_limit_is_not_loaded(tmp_path):
    path = tmp_path / "big"
    path.write_bytes(b"x" * 101)
    with pytest.raises(UnreadableFile, match="more than the 100"):
        read_bytes(path, 100)
    assert read_bytes(path, 101) == b"x" * 101


def test_bytes_that_do_not_decode_are_one_line(tmp_path):
    path = tmp_path / "data.csv"
    path.write_bytes(b"a,b\n\xff\xfe,1\n")
    with pytest.raises(UnreadableFile) as err:
        read_text(path, 100)
    assert "not utf-8 text" in str(err.value) and "\n" not in str(err.value)


def test_missing_and_directory(tmp_path):
    with pytest.raises(UnreadableFile, match="No such file"):
        read_bytes(tmp_path / "nope", 10)
    with pytest.raises(UnreadableFile, match="a directory"):
        read_bytes(tmp_path, 10)
