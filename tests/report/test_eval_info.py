"""``eval_info.json`` in lerobot-eval's layout (lq_ros/report/eval_info.py)."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pandas as pd
import pytest

from lq_ros.report.eval_info import EVAL_INFO_DIR, EVAL_INFO_FILE, eval_info, write_eval_info

LEROBOT_EVAL = Path(__file__).resolve().parents[2] / ".venv-lerobot06" / "lib"


def rows() -> pd.DataFrame:
    base = {"policy": "lerobot", "suite": "libero_spatial", "seed": 7, "latency_dist": "", "policy_seed": 12345}
    out = []
    for mode, latency in (("sync", 0.0), ("async", 0.2)):
        for task, init, status in ((0, 0, "success"), (0, 1, "failure"), (1, 0, "success"), (1, 1, "error")):
            name = f"{mode}_{task}_{init}"
            out.append({**base, "mode": mode, "latency_s": latency, "task": task, "init": init, "status": status,
                        "episode": name})  # fmt: skip
    return pd.DataFrame(out)


def test_one_file_per_protocol_cell_in_lerobot_evals_layout(tmp_path):
    written = write_eval_info(rows(), tmp_path)
    assert sorted(p.relative_to(tmp_path / EVAL_INFO_DIR).as_posix() for p in written) == [
        f"async_200ms/{EVAL_INFO_FILE}",
        f"sync_0ms/{EVAL_INFO_FILE}",
    ]
    info = json.loads((tmp_path / EVAL_INFO_DIR / "sync_0ms" / EVAL_INFO_FILE).read_text())
    # A run error is no task outcome: out of every list and count, named under errors.
    assert [e["success"] for e in info["per_episode"]] == [True, False, True]
    assert [e["episode_ix"] for e in info["per_episode"]] == [0, 1, 2]
    assert info["per_episode"][0] | {} == {
        "episode_ix": 0, "sum_reward": 1.0, "max_reward": 1.0, "success": True, "seed": 7, "suite": "libero_spatial",
        "task": 0, "init": 0, "policy_seed": 12345,
    }  # fmt: skip
    assert info["aggregated"]["pc_success"] == pytest.approx(200 / 3)
    assert info["overall"]["pc_success"] == info["per_group"]["libero_spatial"]["pc_success"]
    assert info["overall"]["n_episodes"] == 3 and info["errors"] == ["sync_1_1"]
    assert [(t["task_id"], t["metrics"]["successes"]) for t in info["per_task"]] == [(0, [True, False]), (1, [True])]


def test_every_key_is_one_lerobot_eval_writes():
    """The names come from LeRobot 0.6.1's lerobot_eval.py (read as text: its import needs the LIBERO simulator)."""
    sources = sorted(LEROBOT_EVAL.glob("python3*/site-packages/lerobot/scripts/lerobot_eval.py"))
    if not sources:
        pytest.skip("LeRobot 0.6's venv is not installed (make setup-lerobot06)")
    written = set(re.findall(r'"(\w+)"', sources[0].read_text()))
    info = eval_info(rows()[rows()["mode"] == "sync"])
    ours = {"errors", "suite", "task", "init", "policy_seed"}  # additions, named in the module docstring
    keys = set(info) | set(info["per_episode"][0]) | set(info["aggregated"]) | set(info["overall"])
    keys |= set(info["per_task"][0]) | set(info["per_task"][0]["metrics"]) | set(info["per_group"]["libero_spatial"])
    assert keys - ours <= written, sorted(keys - ours - written)
