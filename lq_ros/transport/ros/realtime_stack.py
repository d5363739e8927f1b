"""Launch one real-time episode (``--clock realtime``): wall-clock sim, or a robot through the bridge.

Processes (each its own OS process, the run's ROS_DOMAIN_ID, localhost discovery unless the user set
it, PR_SET_PDEATHSIG; lq_ros.transport.ros.stack's helpers):

- ``--clock realtime``: realtime_sim, realtime_policy, realtime_executor, realtime_recorder;
- ``--robot R``: bridge (instead of the sim) + the same three, against robot R's standard topics
  (config/robots/R.yaml); with the stand-in (``--robot standin``) the robot_standin program is started
  too, as a robot of its own, unless the user runs it (``start_standin=False``).

Before anything starts, a policy that needs what the robot does not publish is refused (one line,
lq_ros.robot.observation_builder.check_requirements). Afterwards every process is stopped, Fast DDS files left in
/dev/shm by a killed one are removed, and the logs are copied into the bag folder.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from lq_ros.core.run_config import RunConfig
from lq_ros.recording.episode_folder import logs_dir
from lq_ros.robot.observation_builder import Requirements, check_requirements
from lq_ros.robot.robot_config import RobotConfig, load_robot_config
from lq_ros.transport.processes import ShmTracker, die_with_parent, stop_processes
from lq_ros.transport.ros.stack import child_environment, params_yaml, reserved_domain
from lq_ros.wire.node_names import NODE_NAMES

#: Node programs of a real-time run (module under lq_ros_nodes), by role.
SIM_PROGRAMS = {"sim": "realtime_sim_node", "policy": "realtime_policy_node", "executor": "realtime_executor_node",
                "metrics": "realtime_recorder_node"}  # fmt: skip
ROBOT_PROGRAMS = {"bridge": "bridge_node", "policy": "realtime_policy_node", "executor": "realtime_executor_node",
                  "metrics": "realtime_recorder_node"}  # fmt: skip
STANDIN_PROGRAM = "robot_standin"


def robot_recorded_topics(robot: RobotConfig) -> list[dict]:
    """The robot's topics a bag keeps: joint and finger states, EE pose, the bridge's commands, success, /clock."""
    topics = [robot.joint_states, robot.ee_pose, robot.ee_target]
    if robot.gripper_state:
        topics.append(robot.gripper_state)
    if robot.clock_stream:  # a robot on sim time: its clock, next to the stamps it explains
        topics.append(robot.clock_stream)
    out = [{"name": s.topic, "type": s.type} for s in topics]
    if robot.gripper_command:
        out.append({"name": robot.gripper_command.topic, "type": robot.gripper_command.type})
    if robot.success:
        out.append({"name": robot.success.topic, "type": robot.success.type})
    return out


def check_robot(cfg: RunConfig, policy) -> RobotConfig:
    """The robot's interface, refused (ValueError, one line) if it cannot feed ``policy``."""
    robot = load_robot_config(cfg.robot)
    check_requirements(Requirements.of(policy), robot, cfg.policy)
    return robot


def realtime_parameters(cfg: RunConfig, bag_path: Path, policy, camera_size_px: int, robot: RobotConfig | None) -> dict:
    cams = list(policy.camera_names) or [""]  # (copied per node below: the ROS params parser refuses YAML aliases)
    recorder = {
        "bag_path": str(bag_path), "cameras": list(cams), "camera_size_px": camera_size_px,
        "policy_params_json": json.dumps(policy.params()),
    }  # fmt: skip
    params = {"/**": cfg.ros_parameters(), NODE_NAMES["sim"]: {"cameras": list(cams), "camera_size_px": camera_size_px}}
    if robot is not None:
        req = Requirements.of(policy)
        params[NODE_NAMES["bridge"]] = {"cameras": list(cams), "needs_object_poses": req.objects}
        recorder.update(
            robot_topics_json=json.dumps(robot_recorded_topics(robot)), robot_json=json.dumps(robot.to_dict()),
            ee_topic=robot.ee_pose.topic, joint_topic=robot.joint_states.topic,
            # A robot's topics come at its own rates: score them at those (rows name the rates).
            trajectory_rate="native", energy_rate="native",
        )  # fmt: skip
        params[NODE_NAMES["robot"]] = {"robot_config": str(robot.source), "camera_size_px": camera_size_px}
    params[NODE_NAMES["metrics"]] = recorder
    return params


def launch_realtime(
    cfg: RunConfig,
    out_dir: Path,
    *,
    domain_id: int | None = None,
    timeout_s: float | None = None,
    start_standin: bool | None = None,
    node_parameters: dict[str, dict] | None = None,
) -> tuple[Path, str]:
    """Run one real-time episode; returns its bag folder and the launch error ("" if none).

    ``node_parameters``: extra parameters by node name (e.g. ``{"lq_sim": {"step_delay_s": 0.06}}``).
    """
    from lq_ros.policies import make_policy

    if cfg.clock != "realtime":
        raise ValueError("launch_realtime runs --clock realtime episodes")
    bag_path = Path(out_dir) / cfg.episode_name()
    probe = make_policy(cfg.policy, **cfg.policy_args)
    try:
        robot = check_robot(cfg, probe) if cfg.robot else None
        camera_size_px = cfg.camera_size_for(probe.render_size)
        params = realtime_parameters(cfg, bag_path, probe, camera_size_px, robot)
        for node, extra in (node_parameters or {}).items():
            params[node] = {**params.get(node, {}), **extra}
    finally:
        probe.close()
    if start_standin is None:
        start_standin = robot is not None and robot.name == "libero_standin"
    programs = dict(ROBOT_PROGRAMS if robot is not None else SIM_PROGRAMS)
    if start_standin:
        programs = {"robot": STANDIN_PROGRAM, **programs}
    timeout_s = timeout_s or 120.0 + cfg.budget * 0.05 * 2
    work = Path(tempfile.mkdtemp(prefix="lq_rt_"))
    params_file = work / "params.yaml"
    params_file.write_text(params_yaml(params))
    procs: dict[str, subprocess.Popen] = {}
    shm = ShmTracker()
    reason = ""
    with reserved_domain(domain_id) as domain:
        env = child_environment(domain.id, work / "ros_logs")
        try:
            for role, module in programs.items():
                argv = [sys.executable, "-m", f"lq_ros_nodes.{module}", "--ros-args", "--params-file", str(params_file)]
                with open(work / f"{role}.log", "wb") as log:
                    procs[role] = subprocess.Popen(
                        argv,
                        env=env, stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                        preexec_fn=die_with_parent, pass_fds=(domain.lock_fd,),
                    )  # fmt: skip
            deadline = time.monotonic() + timeout_s
            while True:
                shm.sample(p.pid for p in procs.values() if p.returncode is None)
                if procs["metrics"].poll() is not None:
                    if procs["metrics"].returncode != 0:
                        reason = f"metrics node exited with code {procs['metrics'].returncode}"
                    break
                crashed = [n for n, p in procs.items() if p.poll() is not None]
                if crashed:
                    reason = ", ".join(f"{n} node exited with code {procs[n].returncode}" for n in crashed)
                    break
                if time.monotonic() > deadline:
                    reason = f"episode did not end within {timeout_s:.0f} s (wall clock)"
                    break
                time.sleep(0.25)
        finally:
            shm.sample(p.pid for p in procs.values() if p.returncode is None)
            stop_processes(procs)
            removed = shm.cleanup()
            if removed:
                (work / "launcher.log").write_text(f"removed orphaned Fast DDS files from /dev/shm: {removed}\n")
            dest = logs_dir(bag_path)
            dest.mkdir(parents=True, exist_ok=True)
            for log in work.glob("*.log"):
                shutil.copy(log, dest / log.name)
            shutil.rmtree(work, ignore_errors=True)
    return bag_path, reason
