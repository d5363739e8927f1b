"""The durable store of a sweep folder: only whole, consistent records count as finished."""

from __future__ import annotations

import json

from lq_ros.run import sweep as sw
from tests.run.sweep.test_spec import small_spec


def test_half_written_or_orphaned_results_do_not_count_as_finished(tmp_path):
    spec = sw.expand_spec(small_spec())
    store, jobs, done = sw.prepare(spec, tmp_path)
    assert done == 0 and len(jobs) == 4
    a, b, c, d = (cfg.key() for cfg in spec.configs)
    full = {"key": a, "status": "failure", "bag": None, "row": {}, "attempts": [], "code": jobs[0].code}
    store.write(full)
    text = json.dumps({**full, "key": b})
    store.record_path(b).write_text(text[: len(text) // 2])  # killed while writing (without atomic rename)
    (store.results / f".{c}.json.123.tmp").write_text(json.dumps({**full, "key": c}))  # rename never happened
    store.write({**full, "key": d, "bag": "bags/gone"})  # points at a bag that is not there
    assert store.load(a) is not None
    assert store.load(b) is None and store.load(c) is None and store.load(d) is None
    _, jobs, done = sw.prepare(spec, tmp_path)
    assert done == 1 and {j.key for j in jobs} == {b, c, d}
    assert json.loads((tmp_path / "manifest.json").read_text())["episodes"].keys() == {a, b, c, d}
