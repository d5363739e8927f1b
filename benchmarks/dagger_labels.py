"""What the expert's labels look like in a DAgger dataset, per driver and outcome (``lq collect --latency-ticks``).

Prints, for each (driver, protocol, episode succeeded or not): episodes, frames, and the standard deviation of the
expert's labels (``action``) and of the executed commands (``action.executed``) per action dimension
(dx dy dz droll dpitch dyaw gripper). Large rotation labels where the executed rotations are small mean the
expert asks for corrections the driver never made.

Usage: python benchmarks/dagger_labels.py DATASET [DATASET ...]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import lq_ros  # noqa: F401 - first: it pins OpenBLAS's kernels before numpy loads them (lq_ros/__init__.py)

# isort: split

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from lq_ros.training.dataset import read_frames  # noqa: E402


def label_table(root: Path) -> list[dict]:
    _, cols = read_frames(root)
    meta = [json.loads(line) for line in (root / "meta" / "episodes.jsonl").read_text().splitlines()]
    ep = cols["episode_index"]
    ended = np.zeros(int(ep.max()) + 1, bool)
    np.logical_or.at(ended, ep, cols["next.success"].astype(bool))
    groups: dict[tuple, list[int]] = {}
    for m in meta:
        key = (m.get("driver", "expert"), m.get("mode", "-"), bool(ended[m["episode_index"]]))
        groups.setdefault(key, []).append(m["episode_index"])
    rows = []
    for (driver, mode, ok), ids in sorted(groups.items()):
        sel = np.isin(ep, ids)
        rows.append({"driver": driver, "mode": mode, "success": ok, "episodes": len(ids), "frames": int(sel.sum()),
                     "label_std": [round(float(v), 2) for v in cols["action"][sel].std(0)],
                     "executed_std": [round(float(v), 2) for v in cols["action.executed"][sel].std(0)]})  # fmt: skip
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("data", type=Path, nargs="+")
    args = ap.parse_args()
    for root in args.data:
        print(f"{root.name}: std per dim (dx dy dz droll dpitch dyaw gripper)")
        for r in label_table(root):
            outcome = "success" if r["success"] else "failure"
            print(f"  {r['driver']:9s} {r['mode']:5s} {outcome:7s} episodes {r['episodes']:3d} frames {r['frames']:6d}"
                  f"  labels {r['label_std']}  executed {r['executed_std']}")  # fmt: skip


if __name__ == "__main__":
    main()
