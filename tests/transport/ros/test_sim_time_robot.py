"""A robot that stamps in simulated time (``clock: sim``): its interface, what a run records, the stand-in's clock."""

from __future__ import annotations

import pytest
import yaml

from lq_ros.robot.robot_config import CLOCK, ROBOTS_DIR, parse_robot_config


def _standin(clock: str):
    raw = yaml.safe_load((ROBOTS_DIR / "standin.yaml").read_text())
    raw["clock"] = clock
    return parse_robot_config(raw, "standin_sim.yaml")


def test_a_sim_time_robot_has_a_clock_topic_and_a_wall_clock_one_none() -> None:
    sim, wall = _standin("sim"), _standin("wall")
    assert sim.clock_stream is not None and (sim.clock_stream.topic, sim.clock_stream.type) == ("/clock", CLOCK)
    assert sim.topic_map()["clock"] == "/clock" and sim.to_dict()["clock"] == "sim"
    assert wall.clock_stream is None and "clock" not in wall.topic_map()


def test_the_robots_clock_is_recorded_only_when_it_runs_on_sim_time() -> None:
    sim = {t["name"]: t["type"] for t in _standin("sim").recorded_topics()}
    assert sim["/clock"] == CLOCK
    assert "/clock" not in {t["name"] for t in _standin("wall").recorded_topics()}


@pytest.mark.slow  # one LIBERO scene (~3 s)
@pytest.mark.sim
def test_standin_sim_time_is_mujocos_time_in_whole_substeps() -> None:
    from lq_ros.core.suite_constants import SUBSTEPS_PER_TICK
    from lq_ros.sim.standin_robot import StandinRobot

    robot = StandinRobot("libero_spatial", 0)
    robot.reset(0, 7)
    try:
        t0 = robot.time_ns()
        assert t0 == round(robot._data.time * 1e9) and 0 < t0 < 10**10  # seconds of sim time, not wall time
        for _ in range(SUBSTEPS_PER_TICK):
            robot.substep()
        assert robot.time_ns() - t0 == 50_000_000 and robot.time_ns() == round(robot._data.time * 1e9)
    finally:
        robot.close()
