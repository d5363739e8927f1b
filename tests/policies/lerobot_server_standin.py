"""A stand-in policy served by ``lerobot_server.serve`` (the server's wire layer, without LeRobot), for tests.

Run as ``python lerobot_server_standin.py [AUTH_TIMEOUT_S]``; prints the server's ready line. The stand-in's
answer tells what it has seen: every action row is ``[episodes reset so far, last seed, request count, 0...]``;
``observation/joint_pos[0]`` is a delay to sleep (s, at most 5) before answering; prompt ``"fail"`` raises.
"""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "lq_ros" / "policies"))
import lerobot_server  # noqa: E402 - by path, as LeRobot's venv loads it


class Standin:
    image_keys = ["observation.images.image"]

    def __init__(self) -> None:
        self.episodes, self.seed, self.requests = 0, 0, 0

    def metadata(self) -> dict:
        return {"server": "lq-lerobot-standin"}

    def answer(self, request: dict) -> dict:
        self.requests += 1
        if request["reset"]:
            self.episodes += 1
            self.seed = request["seed"] or 0
        time.sleep(min(float(request["observation/joint_pos"][0]), 5.0))
        if request["prompt"] == "fail":
            raise RuntimeError("stand-in policy failed\n  on purpose")
        row = [self.episodes, self.seed, self.requests, 0, 0, 0, 0]
        return {"actions": np.array([row, row], np.float32), "policy_timing": {"infer_ms": 0.0}}


if __name__ == "__main__":
    if len(sys.argv) > 1:
        lerobot_server.AUTH_TIMEOUT_S = float(sys.argv[1])
    lerobot_server.exit_with_parent(os.getppid())
    lerobot_server.serve(Standin(), "127.0.0.1", 0, sys.stdout)
