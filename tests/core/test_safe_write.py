"""lq_ros/core/safe_write.py: files written into folders the stack did not make never follow a link; CSV text cells
never start like a formula; an output folder is this user's."""

from __future__ import annotations

import os

import pandas as pd
import pytest

from lq_ros.core import safe_write
from lq_ros.core.safe_write import WriteRefused, csv_cell, output_folder, write_csv, write_text


@pytest.fixture
def outside(tmp_path):
    """A file outside the written folder that a planted link points at: it must never change."""
    path = tmp_path / "outside.sh"
    path.write_text("echo mine\n")
    return path


def test_a_link_at_the_target_is_refused_and_not_followed(tmp_path, outside):
    folder = tmp_path / "bags"
    folder.mkdir()
    (folder / "report.md").symlink_to(outside)
    with pytest.raises(WriteRefused, match="report.md: a symbolic link"):
        write_text(folder / "report.md", "# report\n")
    assert outside.read_text() == "echo mine\n"
    assert (folder / "report.md").is_symlink()  # left as found: the user sees what was planted


def test_a_link_at_the_temporary_name_is_never_followed(tmp_path, outside, monkeypatch):
    """Even if someone guessed the temporary name and planted a link there, O_EXCL | O_NOFOLLOW refuses it."""
    folder = tmp_path / "bags"
    folder.mkdir()
    monkeypatch.setattr(safe_write.secrets, "token_hex", lambda n: "guessed")
    (folder / ".episodes.csv.guessed.tmp").symlink_to(outside)
    with pytest.raises(WriteRefused, match="episodes.csv: cannot write"):
        write_text(folder / "episodes.csv", "a,b\n")
    assert outside.read_text() == "echo mine\n"
    assert not (folder / "episodes.csv").exists()


def test_a_write_replaces_a_file_whole_and_leaves_no_temporary(tmp_path):
    target = tmp_path / "t.txt"
    target.write_text("old")
    write_text(target, "new")
    assert target.read_text() == "new" and sorted(p.name for p in tmp_path.iterdir()) == ["t.txt"]
    with pytest.raises(RuntimeError), safe_write.replacing(target) as f:
        f.write("half")
        raise RuntimeError
    assert target.read_text() == "new" and sorted(p.name for p in tmp_path.iterdir()) == ["t.txt"]


def test_a_figure_is_saved_without_following_a_link(tmp_path, outside):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig = plt.figure()
    (tmp_path / "fig.png").symlink_to(outside)
    with pytest.raises(WriteRefused):
        safe_write.save_figure(fig, tmp_path / "fig.png")
    safe_write.save_figure(fig, tmp_path / "other.png", dpi=20)
    plt.close(fig)
    assert outside.read_text() == "echo mine\n"
    assert (tmp_path / "other.png").read_bytes().startswith(b"\x89PNG")


@pytest.mark.parametrize(
    "text, expected",
    [
        ('=HYPERLINK("http://x")', '\'=HYPERLINK("http://x")'),
        ("+1+cmd|' /C calc'!A0", "'+1+cmd|' /C calc'!A0"),
        ("-2+3", "'-2+3"),
        ("@SUM(A1)", "'@SUM(A1)"),
        ("\t=1", "'\t=1"),
        ("\r=1", "'\r=1"),
        ("-0.2", "-0.2"),  # text that is a plain number stays as it is
        ("+1e-3", "+1e-3"),
        ("$(touch x);#", "$(touch x);#"),  # not a formula: a CSV is data (and never written through a link)
        ("sync", "sync"),
    ],
)
def test_csv_text_cells_never_start_like_a_formula(text, expected):
    assert csv_cell(text) == expected


def test_write_csv_escapes_text_and_keeps_numbers(tmp_path):
    frame = pd.DataFrame({"policy": ["=1+1", "ok", None], "x": [-1.5, 2.0, 3.0], "n": [-1, 2, 3]})
    write_csv(frame, tmp_path / "t.csv")
    back = pd.read_csv(tmp_path / "t.csv")
    assert back["policy"].tolist()[:2] == ["'=1+1", "ok"] and pd.isna(back["policy"][2])
    assert back["x"].tolist() == [-1.5, 2.0, 3.0] and back["n"].tolist() == [-1, 2, 3]
    assert frame["policy"][0] == "=1+1"  # the caller's frame is not changed


def test_output_folder_refuses_a_file_a_dangling_link_and_follows_only_when_asked(tmp_path):
    (tmp_path / "file").write_text("x")
    with pytest.raises(WriteRefused, match="--out .*file: a file, not a folder"):
        output_folder(tmp_path / "file")
    (tmp_path / "dangling").symlink_to(tmp_path / "nowhere")
    with pytest.raises(WriteRefused, match="dangling"):
        output_folder(tmp_path / "dangling")
    assert not (tmp_path / "nowhere").exists()
    (tmp_path / "real").mkdir()
    (tmp_path / "link").symlink_to(tmp_path / "real")
    assert output_folder(tmp_path / "link") == tmp_path / "link"  # a folder the user named may be a link
    with pytest.raises(WriteRefused, match="a symbolic link; not followed"):
        output_folder(tmp_path / "link", "report folder", follow=False)
    assert output_folder(tmp_path / "new" / "deeper").is_dir()


@pytest.mark.skipif(os.getuid() != 0, reason="giving a folder to another user needs root")
def test_output_folder_refuses_another_users_folder(tmp_path):
    theirs = tmp_path / "theirs"
    theirs.mkdir()
    os.chown(theirs, 12345, 12345)
    with pytest.raises(WriteRefused, match="a folder of user id 12345, not this user's"):
        output_folder(theirs)


def test_a_file_written_by_name_goes_to_a_fresh_temporary_then_refuses_a_linked_target(tmp_path, outside):
    """lq replay's video is written by ffmpeg, which opens a name: a fresh file, then a rename onto the target."""
    video = tmp_path / "ep.mp4"
    tmp = safe_write.reserve_temporary(video)
    assert tmp.parent == tmp_path and tmp.name.startswith(".ep.mp4.") and tmp.stat().st_size == 0
    tmp.write_bytes(b"frames")
    safe_write.commit(tmp, video)
    assert video.read_bytes() == b"frames" and not tmp.exists()
    (tmp_path / "linked.mp4").symlink_to(outside)
    with pytest.raises(WriteRefused, match="linked.mp4: a symbolic link"):
        safe_write.reserve_temporary(tmp_path / "linked.mp4")
    assert outside.read_text() == "echo mine\n"
