"""Compare two folders of episode bags episode by episode (the same configurations run twice).

    python benchmarks/compare_bags.py RUN_A RUN_B

Bags are paired by folder name (the name is the configuration). For each pair it prints ``identical``
(every message equal byte for byte, apart from the wall-clock measurements that no rerun repeats:
lq_ros.recording.bag_compare) or the first difference. Exit code 1 if any pair differs or is unpaired.
Used to check that a change of code leaves the demo's bags bit-identical.
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from lq_ros.recording.bag_compare import first_difference  # noqa: E402


def bags(root: Path) -> dict[str, Path]:
    return {p.parent.name: p.parent for p in root.rglob("metadata.yaml")}


def main(argv: list[str]) -> int:
    if len(argv) != 2:
        print(__doc__.strip().splitlines()[2].strip(), file=sys.stderr)
        return 2
    left, right = (bags(Path(a)) for a in argv)
    failed = False
    for name in sorted(set(left) | set(right)):
        if name not in left or name not in right:
            print(f"{name}: only in {argv[0] if name in left else argv[1]}")
            failed = True
            continue
        diff = first_difference(left[name], right[name])
        print(f"{name}: {'identical' if diff is None else diff}")
        failed |= diff is not None
    print(f"{len(set(left) & set(right))} pairs compared")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
