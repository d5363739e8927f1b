"""lq_ros.core.bounded_file: a named file is read once, only if it is a regular file within its bound."""

from __future__ import annotations

import os

import pytest

from lq_ros.core.bounded_file import FileRefused, read_regular_file


def test_reads_a_regular_file_whole(tmp_path):
    path = tmp_path / "trace.txt"
    path.write_bytes(b"0.1\n0.2\n")
    assert read_regular_file(path, 8) == b"0.1\n0.2\n"


def test_refuses_a_file_over_the_bound_naming_it(tmp_path):
    path = tmp_path / "big.yaml"
    path.write_bytes(b"x" * 9)
    with pytest.raises(FileRefused, match=r"^spec .*big\.yaml: 9 bytes; at most 8$"):
        read_regular_file(path, 8, "spec")


def test_refuses_a_fifo_without_blocking(tmp_path):
    fifo = tmp_path / "pipe"
    os.mkfifo(fifo)
    with pytest.raises(FileRefused, match="pipe: not a regular file"):
        read_regular_file(fifo, 1024)


def test_refuses_a_device_without_reading_it():
    with pytest.raises(FileRefused, match="/dev/zero: not a regular file"):
        read_regular_file("/dev/zero", 1024)


def test_a_missing_file_is_one_line(tmp_path):
    with pytest.raises(FileRefused, match=r"missing\.yaml: cannot read \(No such file or directory\)$"):
        read_regular_file(tmp_path / "missing.yaml", 1024, "spec")
