"""lq_ros.core.bounded_file: a named file is read once, only if it is a regular file within its bound."""

from __future__ import annotations

import os

import pytest

from lq_ros.core.bounded_file import RESULTS_FILE_MAX_BYTES, FileRefused, read_regular_file, read_results_json


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


def test_a_results_file_linked_to_dev_zero_is_refused_by_name_unread(tmp_path):
    link = tmp_path / "abc.json"
    link.symlink_to("/dev/zero")
    with pytest.raises(FileRefused, match=r"^results file .*abc\.json: a link, not a regular file$"):
        read_results_json(link)


def test_a_results_file_linked_to_a_regular_file_is_refused_too(tmp_path):
    (tmp_path / "real.json").write_text("{}")
    (tmp_path / "abc.json").symlink_to(tmp_path / "real.json")
    with pytest.raises(FileRefused, match="a link"):
        read_results_json(tmp_path / "abc.json")
    assert read_regular_file(tmp_path / "abc.json", 10) == b"{}"  # a file the user names may be a link


def test_a_results_fifo_neither_blocks_nor_is_read(tmp_path):
    os.mkfifo(tmp_path / "manifest.json")
    with pytest.raises(FileRefused, match=r"manifest .*manifest\.json: not a regular file"):
        read_results_json(tmp_path / "manifest.json", "manifest")


@pytest.mark.parametrize(
    ("content", "problem"),
    [
        (b"x" * (RESULTS_FILE_MAX_BYTES + 1), f"{RESULTS_FILE_MAX_BYTES + 1} bytes; at most {RESULTS_FILE_MAX_BYTES}"),
        (b'{"key": ', "not JSON"),
        (b"\xff\xfe{}", "not UTF-8"),
        (b"[" * 100_000 + b"]" * 100_000, "nested too deep"),
        (b"1" * 5000, "not JSON"),  # an integer past Python's 4,300 digits
    ],
)
def test_a_results_file_that_is_no_bounded_json_is_refused_in_one_line(tmp_path, content, problem):
    (tmp_path / "r.json").write_bytes(content)
    with pytest.raises(FileRefused, match=problem) as info:
        read_results_json(tmp_path / "r.json")
    assert "\n" not in str(info.value) and "r.json" in str(info.value)
