"""Policy node: answers observations with action chunks after the injected latency.

Every chunk is stamped with its observation's time t, the request id, the injected latency dt_sim = N dt_c and
the measured wall-clock inference latency dt_real. N is the request's own draw, computed by the same function
the executor core uses (lq_ros.core.latency.request_latency of the run's distribution, seed and request id).
When it is published depends on the run's ``clock`` (read at every activation):

- ``lockstep``: as soon as it is inferred; the executor applies it at tick t + N (it draws N alike) and the
  recorder logs it there, so the measured inference time never matters;
- ``realtime``: N * dt_c of wall time after its inference finished, so the executor sees it dt_real + dt_sim
  after it asked.

No /clock is used either way.

With merge rtc/rtc_hard the policy also gets the executing prefix (/lq/action_prefix) of the request.
A policy that raises publishes a chunk carrying the error, which ends the episode as an error. The
protocol is lq_ros.transport.ros.endpoints.ChunkServer; only the clock the chunks are held on differs.

Managed node: configure builds the policy (``policy``, ``policy_args``); activate checks it can run the
episode's protocol (merge) and resets the episode state; the policy itself is reset for the task and
seed when the sim announces the episode (STARTED).

Policy arguments are ROS parameters one by one: ``policy_args.<name>`` sets the constructor argument ``name``
(``ros2 param set /lq_policy policy_args.host 10.0.0.5``, ``-p policy_args.host:=...``, or ``policy_args: {host:
...}`` in a params file). They add to, and override, the JSON text ``policy_args`` (what the launcher sets), and
are read at configure like it. A name the (registered) policy does not take is refused when it is set, with the
policy's arguments (a ``package.module:Class``'s names and types at configure, before it is built); setting
``policy_args`` (the JSON) or another ``policy`` clears them: the new value stands alone.
Set ``policy`` first, then its arguments.

Who chooses the policy: any participant of the ROS domain can set this node's parameters between
episodes (``/lq_policy/set_parameters``), but a ``package.module:Class`` policy runs code, so it is built
only if the launching user chose it: it (with the same ``policy_args``) is what the process was started
with (``--params-file`` / ``-p``), or what the params file it was started with says at configure (the
launcher rewrites that file, in its private folder, before every episode). A registered policy name
(``scripted``, ``oft``, ``flow``, ``openpi``, ``openvla``...) may be switched at runtime, unless its arguments
run code (``lerobot``: a Python program and a checkpoint; ``Policy.args_run_code``), which is treated as a
``package.module:Class``. Anything else is refused at configure, with the reason, before the module is imported.
"""

from __future__ import annotations

import array
import dataclasses
import fnmatch
import json
import sys
import time
from pathlib import Path

import yaml
from rcl_interfaces.msg import ParameterDescriptor, SetParametersResult
from rclpy.parameter import Parameter

from lq_ros.core.run_config import RunConfig
from lq_ros.policies import REGISTRY, Policy, is_registered, make_policy, policy_class
from lq_ros.run.validation import check_policy_args
from lq_ros.transport.ros.endpoints import ChunkServer
from lq_ros.transport.ros.rclpy_helpers import EpisodeNode, run_managed
from lq_ros.wire import messages as m
from lq_ros.wire.node_names import NODE_NAMES

NODE_NAME = NODE_NAMES["policy"]
#: ``policy_args.<name>``: one constructor argument of the policy as a parameter of its own.
ARG_PREFIX = "policy_args."


def params_file_paths(argv: list[str]) -> list[Path]:
    """The ``--params-file`` arguments among the ROS arguments of ``argv`` (in order)."""
    paths, in_ros_args = [], False
    for i, arg in enumerate(argv):
        if arg == "--ros-args":
            in_ros_args = True
        elif arg == "--" and in_ros_args:
            in_ros_args = False
        elif in_ros_args and arg == "--params-file" and i + 1 < len(argv):
            paths.append(Path(argv[i + 1]))
    return paths


def policy_in_params_file(path: Path, node_name: str = NODE_NAME) -> tuple[str, dict] | None:
    """(policy, policy_args) a ROS params file sets for the node (``/**``, ``/node`` sections, later ones win);
    None if it sets no policy or cannot be read."""
    try:
        data = yaml.safe_load(path.read_text())
    except (OSError, yaml.YAMLError):
        return None
    merged: dict = {}
    for pattern, section in (data or {}).items() if isinstance(data, dict) else ():
        key = str(pattern) if str(pattern).startswith("/") else f"/{pattern}"
        if fnmatch.fnmatchcase(f"/{node_name}", key) and isinstance(section, dict):
            merged.update(section.get("ros__parameters") or {})
    if not isinstance(merged.get("policy"), str):
        return None
    given = merged.get("policy_args", "{}")
    try:  # the JSON text, or (nested in the file) one parameter per argument
        args = dict(given) if isinstance(given, dict) else json.loads(given)
    except (TypeError, ValueError):
        return None
    if not isinstance(args, dict):
        return None
    args.update({k[len(ARG_PREFIX) :]: v for k, v in merged.items() if k.startswith(ARG_PREFIX)})
    return merged["policy"], args


def refuse_untrusted_policy(policy: str, args: dict, chosen_by_user: list[tuple[str, dict]]) -> None:
    """ValueError unless ``policy`` is a registry name whose arguments run no code (not ``lerobot``: its ``python``
    and checkpoint do) or exactly a (policy, args) the launching user chose."""
    if (policy, args) in chosen_by_user or (is_registered(policy) and not policy_class(policy).args_run_code):
        return
    raise ValueError(
        f"policy {policy!r} with these policy_args was set at runtime, not by the user who launched this node: "
        "a package.module:Class policy runs code, so it is accepted only from the launch (params file or "
        "--ros-args -p policy:=...); at runtime choose a registered policy whose arguments run no code "
        f"({', '.join(sorted(n for n in REGISTRY if not policy_class(n).args_run_code))})"
    )


def plain(value):
    """A ROS parameter value as a policy argument: arrays as lists."""
    return list(value) if isinstance(value, array.array | tuple) else value


class PolicyNode(EpisodeNode):
    CONFIGURE_FIELDS = ("policy", "policy_args")

    def __init__(self) -> None:
        super().__init__(NODE_NAME)
        self.policy: Policy | None = None
        # policy_args.<name> given at launch (-p, a params file): declared now, so they take their values.
        for name in getattr(self, "_parameter_overrides", {}):  # rclpy has no public list of the overrides
            if name.startswith(ARG_PREFIX):
                self._declare_argument(name)
        self.add_pre_set_parameters_callback(self._expand_arguments)
        self.add_on_set_parameters_callback(self._check_arguments)
        # What the launching user chose: the parameters this process starts with (no service call has been
        # served yet), and the params files named on its command line (re-read at configure).
        self.launch_policy = (self.cfg.policy, self.policy_arguments(self.cfg))
        self.params_files = params_file_paths(sys.argv)

    # -- policy_args.<name> ----------------------------------------------------------------------------------
    def _declare_argument(self, name: str) -> None:
        self.declare_parameter(
            name, None, ParameterDescriptor(dynamic_typing=True, description="an argument of the policy's constructor")
        )

    def argument_parameters(self) -> dict[str, object]:
        """The ``policy_args.<name>`` parameters that hold a value: name -> value."""
        return {
            k: plain(p.value) for k, p in self.get_parameters_by_prefix("policy_args").items()
            if p.type_ != Parameter.Type.NOT_SET
        }  # fmt: skip

    def policy_arguments(self, cfg: RunConfig) -> dict:
        """The policy's arguments: the JSON ``policy_args``, each ``policy_args.<name>`` over it."""
        return {**cfg.policy_args, **self.argument_parameters()}

    def _expand_arguments(self, params: list[Parameter]) -> list[Parameter]:
        """Before a set: declare a new ``policy_args.<name>`` (between episodes); when ``policy_args`` or another
        ``policy`` is set, clear every ``policy_args.<name>`` (a NOT_SET value undeclares it)."""
        names = {p.name for p in params}
        current = self.get_parameter("policy").value
        replaced = "policy_args" in names or any(p.name == "policy" and p.value != current for p in params)
        out = list(params)
        if replaced:
            out += [Parameter(ARG_PREFIX + k) for k in self.get_parameters_by_prefix("policy_args") if
                    ARG_PREFIX + k not in names]  # fmt: skip
        if not self.active:  # while active every change is refused anyway ("deactivate first")
            for p in params:
                if p.name.startswith(ARG_PREFIX) and not self.has_parameter(p.name):
                    self._declare_argument(p.name)
        return out

    def _check_arguments(self, params: list[Parameter]) -> SetParametersResult:
        """A ``policy_args.<name>`` a registered policy does not take (or of the wrong type) is refused at once,
        with the policy's arguments. A ``package.module:Class`` is not imported here: configure checks it."""
        from lq_ros.run.validation import InputError, check_policy_args

        policy = next((p.value for p in params if p.name == "policy"), self.get_parameter("policy").value)
        args = {p.name[len(ARG_PREFIX) :]: plain(p.value) for p in params
                if p.name.startswith(ARG_PREFIX) and p.type_ != Parameter.Type.NOT_SET}  # fmt: skip
        if args and is_registered(policy):
            try:
                check_policy_args(policy, args)
            except InputError as exc:
                return SetParametersResult(successful=False, reason=str(exc))
        return SetParametersResult(successful=True)

    def configured_values(self) -> dict:
        return {**super().configured_values(), **{ARG_PREFIX + k: v for k, v in self.argument_parameters().items()}}

    # -- lifecycle -------------------------------------------------------------------------------------------
    def chosen_by_user(self) -> list[tuple[str, dict]]:
        from_files = [policy_in_params_file(path) for path in self.params_files]
        return [self.launch_policy, *(p for p in from_files if p is not None)]

    def configure(self, cfg: RunConfig) -> None:
        cfg = self.cfg = dataclasses.replace(cfg, policy_args=self.policy_arguments(cfg))
        refuse_untrusted_policy(cfg.policy, cfg.policy_args, self.chosen_by_user())  # before any import
        # A package.module:Class's arguments are checked here, once its module may be imported (a registered
        # policy's already were, as each was set): a name it does not take, a value of the wrong type, one line.
        check_policy_args(cfg.policy, cfg.policy_args)
        self.policy = make_policy(cfg.policy, **cfg.policy_args)

    def activate(self, cfg: RunConfig) -> None:
        self.policy.check_merge(cfg.merge)  # refused before the episode starts
        realtime = cfg.clock == "realtime"
        self.server = ChunkServer(
            self.policy, cfg, self.episode_publisher(m.ACTION_CHUNK).publish, self.get_logger(),
            now_ns=time.time_ns, hold_from="inference_end" if realtime else None, on_end=self.seal_episode,
        )  # fmt: skip
        self.server.subscribe(self.episode_subscription)
        if realtime:
            self.episode_timer(0.002, self.server.flush)  # due chunks go out within ~2 ms of their wall time

    def cleanup(self) -> None:
        if self.policy is not None:
            self.policy.close()
            self.policy = None


def main() -> None:
    run_managed(PolicyNode)


if __name__ == "__main__":
    main()
