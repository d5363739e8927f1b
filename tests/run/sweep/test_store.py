"""The durable store of a sweep folder: only whole, consistent records count as finished."""

from __future__ import annotations

import json
import os

import pytest

from lq_ros.run import sweep as sw
from lq_ros.run.sweep.identity import CODE_FIELD, identities
from lq_ros.run.sweep.record_check import FINAL_STATUSES
from tests.run.sweep.test_spec import small_spec


def record(cfg, status: str = "failure", **changes) -> dict:
    """A record as the orchestrator writes it, of ``cfg`` (its row: the fields a row is read by)."""
    success = {"success": True, "failure": False}.get(status)
    cell = {k: getattr(cfg, k) for k in ("policy", "mode", "latency_s", "suite", "task", "init", "seed")}
    row = {"episode": cfg.episode_name(), "status": status, "success": success, **cell}
    out = {"format": 1, "key": cfg.key(), "status": status, "bag": None, "row": row, "attempts": [],
           "config": cfg.to_dict(), CODE_FIELD: identities([cfg])[cfg.key()]}  # fmt: skip
    out.update(changes)
    return out


def test_half_written_or_orphaned_results_do_not_count_as_finished(tmp_path):
    spec = sw.expand_spec(small_spec())
    store, jobs, done = sw.prepare(spec, tmp_path)
    assert done == 0 and len(jobs) == 4
    a, b, c, d = spec.configs
    store.write(record(a))
    text = json.dumps(record(b))
    store.record_path(b.key()).write_text(text[: len(text) // 2])  # killed while writing (without atomic rename)
    (store.results / f".{c.key()}.json.123.tmp").write_text(json.dumps(record(c)))  # rename never happened
    store.write(record(d, bag="bags/gone"))  # points at a bag that is not there
    assert store.load(a.key()) is not None
    assert store.load(b.key()) is None and store.load(c.key()) is None and store.load(d.key()) is None
    _, jobs, done = sw.prepare(spec, tmp_path)
    assert done == 1 and {j.key for j in jobs} == {b.key(), c.key(), d.key()}
    assert json.loads((tmp_path / "manifest.json").read_text())["episodes"].keys() == {x.key() for x in spec.configs}


def test_a_run_errors_row_without_its_configuration_takes_it_from_the_record(tmp_path):
    """A node that died before recording leaves a row of three fields: the record's config places it in its cell."""
    spec = sw.expand_spec(small_spec())
    store, _, _ = sw.prepare(spec, tmp_path)
    cfg = spec.configs[0]
    store.write(record(cfg, "error", row={"episode": cfg.episode_name(), "status": "error", "success": None}))
    loaded = store.load(cfg.key())
    assert loaded is not None and loaded["row"]["policy"] == "sine" and loaded["row"]["latency_s"] == cfg.latency_s
    assert store.refused == {}


def test_a_fifo_or_a_link_to_dev_zero_in_results_is_refused_by_name_and_run_again(tmp_path, no_hang):
    """A resumed sweep neither hangs on a FIFO (the hung sweep would keep its folder locked) nor reads /dev/zero."""
    spec = sw.expand_spec(small_spec())
    store, _, _ = sw.prepare(spec, tmp_path)
    a, b, c, _ = spec.configs
    store.write(record(a))
    os.mkfifo(store.record_path(b.key()))
    store.record_path(c.key()).symlink_to("/dev/zero")
    os.mkfifo(store.attempts / f"{a.key()}.a1.json")
    store = sw.ResultStore(tmp_path)
    assert [store.load(x.key()) is None for x in (a, b, c)] == [False, True, True]
    assert store.refused == {
        f"results/{b.key()}.json": f"results file {store.record_path(b.key())}: not a regular file",
        f"results/{c.key()}.json": f"results file {store.record_path(c.key())}: a link, not a regular file",
    }
    assert [r["key"] for r in store.records()] == [a.key()]
    assert store.failed_attempts(a.key()) == [] and f"attempts/{a.key()}.a1.json" in store.refused


def test_a_contradictory_record_is_not_finished_and_says_why(tmp_path):
    spec = sw.expand_spec(small_spec())
    store, _, _ = sw.prepare(spec, tmp_path)
    a, b, c, d = spec.configs
    bad_row = record(a)["row"] | {"status": "success", "success": True}
    store.write(record(a, "error", row=bad_row))  # the record says error, its row success
    store.write(record(b, attempts=[{"attempt": "1", "status": "error"}]))
    store.write(record(c, row=[record(c)["row"]]))
    store.write(record(d, "done"))
    assert [store.load(x.key()) for x in spec.configs] == [None] * 4
    why = {k.split("/")[1].split(".")[0]: v.split(": ", 1)[1] for k, v in store.refused.items()}
    assert why == {
        a.key(): "status error but the row's status is success",
        b.key(): "attempts[0].attempt '1' is not a whole number >= 1",
        c.key(): "row: the row is a list, not an object of fields",
        d.key(): f"status 'done'; expected one of {', '.join(FINAL_STATUSES)}",
    }


def test_the_lock_is_never_taken_through_a_link_nor_truncated(tmp_path):
    """The lock file was opened following links (O_RDWR | O_CREAT) and truncated: a planted .lock link emptied the
    file it pointed at."""
    outside = tmp_path / "outside.sh"
    outside.write_text("echo mine\n")
    folder = tmp_path / "sweep"
    folder.mkdir()
    (folder / sw.store.LOCK_FILE).symlink_to(outside)
    with pytest.raises(sw.StoreError, match=r"\.lock \(a symbolic link, not followed\)"), sw.ResultStore(folder).lock():
        pass
    assert outside.read_text() == "echo mine\n"
    (folder / sw.store.LOCK_FILE).unlink()
    (folder / sw.store.LOCK_FILE).hardlink_to(outside)  # a second name of one of this user's files
    with pytest.raises(sw.StoreError, match="a hard link"), sw.ResultStore(folder).lock():
        pass
    assert outside.read_text() == "echo mine\n"


def test_the_lock_is_held_once_per_process(tmp_path):
    """lq eval writes its spec under the folder's lock, then runs the sweep, which takes the same lock again."""
    store = sw.ResultStore(tmp_path / "sweep")
    with store.lock(), store.lock():
        assert (tmp_path / "sweep" / sw.store.LOCK_FILE).read_text().split() == [str(os.getpid())]


@pytest.mark.slow
@pytest.mark.sim
def test_a_resumed_sweep_runs_a_fifos_episode_again_and_refuses_a_link_before_it_starts(tmp_path, no_hang):
    """The hung resume would have kept the folder locked: the FIFO is named and its episode runs again, the record
    written in its place a regular file; a link to /dev/zero is refused in one line before anything runs."""
    spec = sw.expand_spec(small_spec(latencies_s=[0.0], modes=["sync"]))
    store = sw.ResultStore(tmp_path)
    store.create()
    (cfg,) = spec.configs
    path = store.record_path(cfg.key())
    path.symlink_to("/dev/zero")
    with pytest.raises(sw.StoreError, match=r"\.json: a link where a results file is written; not followed"):
        sw.run_sweep(spec, tmp_path, workers=1)
    assert not list(store.bags.iterdir())  # nothing ran
    path.unlink()
    os.mkfifo(path)
    summary = sw.run_sweep(spec, tmp_path, workers=1)
    assert summary.ran == 1 and summary.skipped == 0
    assert summary.refused == {f"results/{cfg.key()}.json": f"results file {path}: not a regular file"}
    assert path.is_file() and [r["key"] for r in sw.ResultStore(tmp_path).records()] == [cfg.key()]
