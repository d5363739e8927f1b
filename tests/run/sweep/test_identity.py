"""Results record the code that made them; a resume into a folder of other code's results refuses, naming the change."""

from __future__ import annotations

import json
import textwrap
import uuid

import pytest

from lq_ros.run import sweep as sw
from lq_ros.run.sweep.identity import CODE_FIELD, changes, code_identity
from tests.run.sweep.test_spec import small_spec

POLICY = """
import numpy as np

from lq_ros.policies.base import Policy


class Mine(Policy):
    name = "mine"

    def __init__(self, gain: float = {gain}, chunk_size: int = 4) -> None:
        self.gain, self.chunk_size = gain, chunk_size

    def reset(self, task, seed) -> None:
        pass

    def infer(self, obs):
        chunk = np.zeros((self.chunk_size, 7))
        chunk[:, 0] = self.gain
        chunk[:, 6] = -1.0
        return chunk
"""


def write_policy(folder, module: str, gain: float) -> str:
    (folder / f"{module}.py").write_text(textwrap.dedent(POLICY.format(gain=gain)))
    return f"{module}:Mine"


@pytest.fixture
def policy_module(tmp_path, monkeypatch):
    """A user's own policy module in tmp_path (importable by the spawned sweep workers too)."""
    folder = tmp_path / "code"
    folder.mkdir()
    monkeypatch.syspath_prepend(str(folder))
    return folder, f"mine_{uuid.uuid4().hex[:8]}"


def test_identity_holds_class_source_hash_effective_args_and_version(policy_module):
    folder, module = policy_module
    name = write_policy(folder, module, 0.1)
    ident = code_identity(name, {"chunk_size": 6})
    assert ident["policy_class"] == f"{module}:Mine"
    assert ident["policy_args"] == {"gain": 0.1, "chunk_size": 6}  # the default is recorded, not only the given
    assert ident["lq_ros"] and ident["git_commit"] and len(ident["lq_ros_source_sha256"]) == 16
    before = ident["policy_source_sha256"]
    (folder / f"{module}.py").write_text((folder / f"{module}.py").read_text() + "\n# an edit\n")
    assert code_identity(name, {"chunk_size": 6})["policy_source_sha256"] != before  # read from disk, not the cache


def test_a_default_that_is_no_json_value_is_the_same_in_every_process():
    from lq_ros.run.sweep.identity import _plain

    class Thing:
        pass

    assert _plain({"x": Thing()}) == {"x": _plain({"x": Thing()})["x"]}  # (two objects, two addresses)


def test_changes_name_each_difference():
    old = {"policy_class": "m:A", "policy_source_sha256": "1", "policy_args": {"gain": 0.1}, "lq_ros": "0.1.0",
           "lq_ros_source_sha256": "p1", "git_commit": "abc"}  # fmt: skip
    assert changes(old, dict(old)) == []
    new = old | {"policy_source_sha256": "2", "policy_args": {"gain": 0.2}, "lq_ros_source_sha256": "p2"}
    assert changes(old, new) == ["the source of m:A changed", "policy_args.gain 0.1 -> 0.2",
                                 "the source of lq_ros changed"]  # fmt: skip
    assert changes(None, new) == ["the results record no code identity (made by an older lq)"]


def test_a_commit_that_changes_no_code_is_no_change():
    """The commit is provenance: a docs-only commit (or a checkout's +dirty from a docs edit) is the same code."""
    old = {"policy_class": "m:A", "policy_source_sha256": "1", "policy_args": {}, "lq_ros": "0.1.0",
           "lq_ros_source_sha256": "p1", "git_commit": "abc"}  # fmt: skip
    assert changes(old, old | {"git_commit": "def+dirty"}) == []
    # A record made before the project's source was hashed is compared by its commit, as it was then.
    legacy = {k: v for k, v in old.items() if k != "lq_ros_source_sha256"}
    assert changes(legacy, old | {"git_commit": "def"}) == ["git_commit abc -> def"]
    assert changes(legacy, old) == []


def test_the_project_source_hash_follows_code_files_only(tmp_path, monkeypatch):
    import lq_ros
    from lq_ros.run.sweep import identity

    root = tmp_path / "checkout"
    (root / "lq_ros" / "core").mkdir(parents=True)
    (root / "nodes").mkdir()
    (root / "docs").mkdir()
    (root / "lq_ros" / "__init__.py").write_text("")
    (root / "lq_ros" / "core" / "x.py").write_text("X = 1\n")
    (root / "nodes" / "sim_node.py").write_text("N = 1\n")
    (root / "docs" / "guide.md").write_text("text\n")
    monkeypatch.setattr(lq_ros, "__file__", str(root / "lq_ros" / "__init__.py"))
    before = identity.project_source_hash()
    (root / "docs" / "guide.md").write_text("other text\n")
    (root / "lq_ros" / "core" / "notes.txt").write_text("not code\n")
    assert identity.project_source_hash() == before  # docs and data are not the code
    (root / "nodes" / "sim_node.py").write_text("N = 2\n")
    after_node = identity.project_source_hash()
    assert after_node != before  # a node program is code
    (root / "lq_ros" / "core" / "x.py").write_text("X = 2\n")
    assert identity.project_source_hash() not in (before, after_node)


@pytest.mark.slow
@pytest.mark.sim
def test_an_edited_policy_refuses_the_resume_and_overwrite_reruns(tmp_path, policy_module):
    folder, module = policy_module
    name = write_policy(folder, module, 0.1)
    spec = sw.expand_spec(small_spec(policies=[name], latencies_s=[0.0], modes=["sync"], max_steps=4))
    out = tmp_path / "out"
    assert sw.run_sweep(spec, out, workers=1).ran == 1
    record = sw.ResultStore(out).records()[0]
    assert record[CODE_FIELD]["policy_args"] == {"gain": 0.1, "chunk_size": 4}
    assert sw.run_sweep(spec, out, workers=1).skipped == 1  # the same code: resumed, nothing to run
    write_policy(folder, module, 0.3)  # a user changes a default argument
    with pytest.raises(sw.StoreError) as refused:
        sw.run_sweep(spec, out, workers=1)
    message = str(refused.value)
    assert "\n" not in message and "1 of its 1 finished episodes were made by other code" in message
    assert f"the source of {module}:Mine changed" in message and "--overwrite" in message
    again = sw.run_sweep(spec, out, workers=1, overwrite=True)
    assert again.ran == 1 and again.skipped == 0
    rerun = json.loads(sw.ResultStore(out).record_path(record["key"]).read_text())
    assert rerun[CODE_FIELD]["policy_source_sha256"] != record[CODE_FIELD]["policy_source_sha256"]
    assert rerun[CODE_FIELD]["policy_args"]["gain"] == 0.3  # the worker ran the edited code, and it is recorded
    assert sw.run_sweep(spec, out, workers=1).skipped == 1
