"""The shipped top-level folders: the installed package's copy when there is one, else the source tree's."""

from __future__ import annotations

from lq_ros.core import shipped
from lq_ros.robot.robot_config import ROBOTS_DIR
from lq_ros.wire.messages import MSG_DIR


def test_every_shipped_folder_exists_in_the_source_tree_with_files():
    for folder, pattern in shipped.SHIPPED.items():
        assert sorted((shipped.REPO_ROOT / folder).glob(pattern)), folder


def test_a_checkout_reads_them_in_place():
    assert not shipped.SHIPPED_DIR.exists()  # only a built package has a copy
    assert MSG_DIR == shipped.REPO_ROOT / "msg_schemas" / "lq_msgs" / "msg"
    assert ROBOTS_DIR == shipped.REPO_ROOT / "config" / "robots"


def test_the_installed_copy_is_preferred(tmp_path, monkeypatch):
    monkeypatch.setattr(shipped, "SHIPPED_DIR", tmp_path)
    assert shipped.shipped_path("config/robots") == shipped.REPO_ROOT / "config" / "robots"  # no copy: the tree's
    (tmp_path / "config" / "robots").mkdir(parents=True)
    assert shipped.shipped_path("config/robots") == tmp_path / "config" / "robots"
