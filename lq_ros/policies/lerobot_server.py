"""Serve a LeRobot checkpoint to the stack over the openpi websocket protocol (runs in LeRobot's own venv).

LeRobot pins its own torch (0.4.4: < 2.11; this project pins 2.13), so LeRobot lives in a separate
environment (``make setup-lerobot``: LeRobot 0.4.4 on Python 3.11, ``.venv-lerobot``; ``make setup-lerobot06``:
LeRobot 0.6 on Python 3.12, ``.venv-lerobot06``) and this file runs there, started and stopped by
:class:`lq_ros.policies.lerobot_client.LeRobotPolicy` on 127.0.0.1 only. The same file serves both LeRobot
versions. It imports nothing from ``lq_ros`` (the package is not installed in that venv): stdlib, numpy, torch,
lerobot, websockets and msgpack.

What the policy sees is built by LeRobot's own code, step by step as ``lerobot-eval`` builds it
(``lerobot/scripts/lerobot_eval.py: rollout``): the raw observation dict of ``lerobot.envs.libero.LiberoEnv``
(``pixels``/``robot_state``, with the leading batch axis of its vector env), then ``preprocess_observation``,
the task string, the LIBERO env processor (``make_env_pre_post_processors``: 180-degree image rotation,
8-D state with LeRobot's float32 axis-angle), the checkpoint's saved pre-processor, the policy, its saved
post-processor and the env post-processor, action by action.

One chunk per request. By default the request clears the policy's action queue and calls ``select_action``
once, as ``lerobot-eval`` does on the tick its queue runs dry, then takes the rest of the refilled queue, so
the chunk is exactly the ``n_action_steps`` actions ``lerobot-eval`` would execute from that observation
(``--n-action-steps`` overrides the checkpoint's). With ``--full-chunk``, and always for a policy that keeps no
action queue (ACT with temporal ensembling: the stack's executor merges the chunks instead), the answer is the
whole chunk of ``predict_action_chunk``. A request that carries a prefix (``--merge rtc``/``rtc_hard``) is
answered by ``predict_action_chunk`` with LeRobot's own RTC processor guiding the chunk (SmolVLA, pi0, pi0.5: the
flow-matching policies LeRobot wires RTC into), as LeRobot's RTC runs it: the checkpoint's ``rtc_config`` or LeRobot's
``RTCConfig`` defaults (schedule, execution horizon, maximum guidance weight; ``--rtc-*`` override them), and as the
prefix the model's own leftover of its previous chunk, as many rows as the executor's plan has left (the request's
``prefix/schedule`` ``hard``, ``--merge rtc_hard``, selects the ZEROS schedule; any other, the configured one).

Observation history (``n_obs_steps`` n > 1: diffusion's default 2, VQ-BeT's 5): ``lerobot-eval`` calls
``select_action`` every tick, and the policy's observation queue keeps the last n observations (at reset, copies of
the first). The stack asks only at request ticks, so each request carries the n - 1 ticks before its own (captured by
the simulator every tick) and the server hands each of them to ``select_action`` first, with a placeholder in the
action queue for it to pop instead of inferring: the policy's own code queues them, and its queue then holds what
``lerobot-eval``'s would at that tick.

Cameras: the checkpoint's image keys are fed from LIBERO's two cameras through a mapping (``--cameras``, JSON
``{"observation.images.camera1": "image", ...}``, made by the client from the checkpoint's config or the user's
``rename``), applied where ``lerobot-eval --env.camera_name_mapping`` applies it: to the env's pixel keys.
Image keys ``observation.images.empty_camera_<i>`` (SmolVLA's and pi0's ``empty_cameras``) are not sent: the
policy pads them itself, as under ``lerobot-eval``.

Protocol (openpi ``websocket_policy_server``): a metadata frame, then one msgpack-numpy request, one reply.
Request keys: ``token`` (this run's secret, see below); ``observation/images/image`` and ``.../image2`` (the
cameras the mapping uses: uint8 H x W x 3 as robosuite renders them, bottom row first);
``observation/eef_pos``, ``observation/eef_quat`` (x y z w), ``observation/gripper_qpos``,
``observation/joint_pos``, ``observation/joint_vel`` (float); optionally ``observation/eef_mat`` (9 floats: the EE
rotation matrix of robosuite's controller, row-major; LeRobot's env reports it as ``robot_state.eef.mat``, and X-VLA's
LIBERO processor builds its state from it: a request for X-VLA without it is refused); ``prompt``; ``reset`` (true on
an episode's first request: the policy and processors are reset) and ``seed`` (with ``reset``); optionally
``prefix/actions`` (L x 7, the executor's plan in the env's action space), ``prefix/delay`` (d, ticks) and
``prefix/schedule`` (``exp``, ``linear``, ``hard`` or ``ones``); for a policy with ``n_obs_steps`` n > 1,
``history/<field>`` for each observation field above: the n - 1 ticks before the request's, stacked oldest first
along a leading axis (ticks before the episode's first are copies of it). Reply: ``actions`` (n, 7) float32 and
``policy_timing.infer_ms``; for relative actions anchored per tick (``--relative-anchor tick``, the default), the
relative rows and ``anchor_weights`` (7,): the executor adds each tick's state, as ``lerobot-eval`` does. A failure
is sent as one text line (the exception's type and message, no traceback), then the socket closes.

Any local process can reach a loopback port, so the server trusts no peer:

- **Secret**: the server draws a random token per run and prints it in its ready line (a pipe only the
  process that started it reads). A request without it is refused and the connection closed; a connection
  that sends no request within :data:`AUTH_TIMEOUT_S` is closed.
- **Browsers**: a handshake with an ``Origin`` header (every web page's websocket has one) is refused (403).
- **One client at a time**: an authenticated connection is served alone; a second waits until the first
  closes (at most :data:`BUSY_WAIT_S`), so no one can reset or reseed the policy mid-episode.
- **Decoding**: requests are decoded by the project's own msgpack hook (``remote_wire.py``, loaded by path:
  plain numeric dtypes only, byte counts checked), never openpi-client's (it builds object arrays from the
  peer's bytes), and each field is checked (dtype, shape, finite) before LeRobot sees it.

What is loaded is what the user named: ``--path`` is an existing checkpoint folder (loaded offline: nothing is
fetched from a hub, not even a missing state file) or an explicit ``hub:org/name``. The checkpoint's processor
files name the steps LeRobot builds; a step is taken only from LeRobot's registry of processor steps (its
``registry_name``), never a ``class`` path that LeRobot would import and call (a ``subprocess.Popen`` would run),
and its ``state_file`` only from the checkpoint folder, unless ``--trust-processors`` (the user's explicit
``trust_processors=1``).

Modules (siblings of this file, imported by name since lq_ros is not installed in LeRobot's venv): this one serves
(the websocket protocol, authentication, one client at a time); ``lerobot_request.py`` checks each request's fields;
``lerobot_checkpoint.py`` checks the checkpoint (location, processor files, config fields, weights);
``lerobot_runner.py`` is the loaded policy (what it is handed, the chunk it answers).

Usage: ``python lerobot_server.py --path DIR|hub:ORG/NAME [--device cpu] [--threads N] [--port 0] [--cameras JSON]
[--n-action-steps N] [--full-chunk] [--rtc-execution-horizon N] [--rtc-schedule S] [--rtc-max-guidance-weight W]
[--rtc-prefix model|executor]``; prints one
JSON line ``{"ready": true, "port": ..., "token": ...}`` on stdout once the policy is loaded, or one ``error:``
line on stderr and exits 2.
"""

from __future__ import annotations

import argparse
import contextlib
import hmac
import importlib.util
import json
import os
import secrets
import sys
import threading
import time
from pathlib import Path

# The server runs as a script in LeRobot's venv, where lq_ros is not installed: its sibling modules are imported by
# name from this folder (a script's own folder is on sys.path; added for an import by path).
if str(Path(__file__).resolve().parent) not in sys.path:
    sys.path.append(str(Path(__file__).resolve().parent))

from lerobot_checkpoint import HUB_PREFIX, check_config_fields, go_offline  # noqa: E402, F401 - test scripts use these
from lerobot_request import RequestError, checked_request, error_line  # noqa: E402
from lerobot_runner import LeRobotServer  # noqa: E402

#: Longest accepted request, bytes (two 512 px images and the state are ~1.6 MB).
MAX_REQUEST_BYTES = 16 * 1024 * 1024
#: How long a new connection may take to send its first (authenticated) request, s.
AUTH_TIMEOUT_S = 10.0
#: How long an authenticated connection waits for the one being served to close, s.
BUSY_WAIT_S = 300.0
#: Connections allowed to be waiting for their first request at once (each may hold a few frames in memory).
MAX_PENDING = 4
#: Frames websockets may buffer per connection (each at most MAX_REQUEST_BYTES).
MAX_QUEUED_FRAMES = 2


def load_wire():
    """``lq_ros/policies/remote_wire.py`` (the safe msgpack-numpy decoder), by path: lq_ros is not installed here."""
    spec = importlib.util.spec_from_file_location("lq_lerobot_remote_wire", Path(__file__).with_name("remote_wire.py"))
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def pack_numpy(obj: object) -> object:
    """msgpack ``default`` for openpi's msgpack-numpy encoding (what the client's safe hook decodes)."""
    import numpy as np

    if isinstance(obj, np.ndarray):
        if obj.dtype.kind not in "biuf":
            raise TypeError(f"cannot send an array of dtype {obj.dtype}")
        return {b"__ndarray__": True, b"data": obj.tobytes(), b"dtype": obj.dtype.str, b"shape": obj.shape}
    if isinstance(obj, np.generic):
        return {b"__npgeneric__": True, b"data": obj.item(), b"dtype": obj.dtype.str}
    raise TypeError(f"cannot send {type(obj).__name__}")


def serve(server, host: str, port: int, ready_out, token: str | None = None) -> None:
    """Answer one authenticated connection at a time until the process is stopped (see the module docstring).

    ``server`` has ``image_keys``, ``metadata()`` and ``answer(request)``; ``token`` (default: a fresh random
    one) is printed in the ready line on ``ready_out``.
    """
    import msgpack
    from websockets.exceptions import ConnectionClosed
    from websockets.sync.server import serve as websocket_serve

    wire = load_wire()
    token = token or secrets.token_urlsafe(32)
    packer = msgpack.Packer(default=pack_numpy)  # our replies; requests are decoded by the project's safe hook
    metadata = server.metadata()
    serving = threading.Lock()
    pending = threading.BoundedSemaphore(MAX_PENDING)

    def refuse(connection, line: str) -> None:
        with contextlib.suppress(ConnectionClosed, OSError):
            connection.send(line)
        connection.close()

    def request_of(frame: object) -> dict:
        """The frame decoded and authenticated; RequestError (one line) otherwise."""
        if not isinstance(frame, bytes):
            raise RequestError("a request is one binary msgpack frame, got text")
        try:
            request = wire.unpack_msgpack_numpy(frame)
        except wire.UnsafeReply as exc:
            raise RequestError(f"request refused: {exc}") from None
        except Exception as exc:  # noqa: BLE001 - any undecodable frame is garbage
            raise RequestError(f"request is not msgpack-numpy ({type(exc).__name__})") from None
        presented = request.get("token") if isinstance(request, dict) else None
        if not isinstance(presented, str) or not hmac.compare_digest(presented.encode(), token.encode()):
            raise PermissionError("request refused: it does not carry this server's token (from its ready line)")
        return checked_request(request, server.image_keys)

    def handler(connection) -> None:
        if not pending.acquire(blocking=False):
            refuse(connection, f"busy: {MAX_PENDING} connections are already waiting to authenticate")
            return
        try:
            connection.send(packer.pack(metadata))
            frame = connection.recv(timeout=AUTH_TIMEOUT_S)
            request = request_of(frame)
        except TimeoutError:
            refuse(connection, f"TimeoutError: no request within {AUTH_TIMEOUT_S:g} s of connecting")
            return
        except ConnectionClosed:
            return
        except (RequestError, PermissionError) as exc:
            refuse(connection, error_line(exc))
            return
        finally:
            pending.release()
        if not serving.acquire(timeout=BUSY_WAIT_S):
            refuse(connection, f"busy: another client has been served for over {BUSY_WAIT_S:g} s")
            return
        try:
            while True:
                try:
                    reply = server.answer(request)
                except Exception as exc:  # noqa: BLE001 - the client shows this one line as the episode's error
                    refuse(connection, error_line(exc))
                    return
                connection.send(packer.pack(reply))
                try:
                    request = request_of(connection.recv())
                except (RequestError, PermissionError) as exc:
                    refuse(connection, error_line(exc))
                    return
        except ConnectionClosed:
            return
        finally:
            serving.release()

    with websocket_serve(
        handler, host, port, max_size=MAX_REQUEST_BYTES, max_queue=MAX_QUEUED_FRAMES, compression=None,
        origins=[None],  # a handshake with an Origin header (a web page's) is refused with 403
    ) as ws_server:  # fmt: skip
        bound_port = ws_server.socket.getsockname()[1]
        print(json.dumps({"ready": True, "port": bound_port, **metadata, "token": token}), file=ready_out, flush=True)
        ws_server.serve_forever()


def exit_with_parent(parent_pid: int) -> None:
    """Exit once the process that started us is gone (killed with -9, it could not stop us itself)."""

    def watch() -> None:
        while os.getppid() == parent_pid:
            time.sleep(0.5)
        os._exit(0)

    threading.Thread(target=watch, daemon=True).start()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--path", required=True, help="checkpoint directory written by save_pretrained")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--threads", type=int, default=0, help="torch intra-op threads (0: torch's default)")
    parser.add_argument("--host", default="127.0.0.1")
    parser.add_argument("--port", type=int, default=0, help="0: any free port (printed in the ready line)")
    parser.add_argument("--suite", default="libero_spatial", help="LIBERO suite (selects LeRobot's env processor)")
    parser.add_argument("--parent-pid", type=int, default=0, help="exit when this process is gone (0: never)")
    parser.add_argument(
        "--trust-processors", action="store_true", help="load processor steps by class path (runs their code)"
    )
    parser.add_argument("--cameras", default=None, help='JSON: image key -> env camera ("image" or "image2")')
    parser.add_argument("--n-action-steps", type=int, default=None, help="actions per chunk (default: the config's)")
    parser.add_argument("--full-chunk", action="store_true", help="answer with predict_action_chunk's whole chunk")
    parser.add_argument("--rtc-execution-horizon", type=int, default=None, help="RTCConfig.execution_horizon")
    parser.add_argument("--rtc-schedule", default=None, help="RTCConfig.prefix_attention_schedule (linear, exp, ...)")
    parser.add_argument("--rtc-max-guidance-weight", type=float, default=None, help="RTCConfig.max_guidance_weight")
    parser.add_argument("--rtc-prefix", default="model", help="model (LeRobot's: the leftover) or executor (the plan)")
    parser.add_argument("--empty-cameras", type=int, default=None, help="camera inputs the policy pads (the config's)")
    parser.add_argument("--relative-anchor", default="tick", help="tick (lerobot-eval's) or chunk: see lerobot_runner")
    args = parser.parse_args(argv)
    rtc = {
        key: value
        for key, value in (
            ("execution_horizon", args.rtc_execution_horizon),
            ("prefix_attention_schedule", args.rtc_schedule),
            ("max_guidance_weight", args.rtc_max_guidance_weight),
        )
        if value is not None
    }
    # stdout carries the ready line alone: anything LeRobot prints ("Loading weights ...") goes to stderr.
    ready_out, sys.stdout = sys.stdout, sys.stderr
    if args.parent_pid:
        exit_with_parent(args.parent_pid)
    if args.host not in ("127.0.0.1", "localhost", "::1"):
        print(f"error: --host {args.host!r}: the policy server binds to loopback only (127.0.0.1)", file=sys.stderr)
        return 2
    try:
        if not args.path.startswith(HUB_PREFIX):
            go_offline()  # before anything imports a hub library: each reads the switches once, when imported
        import torch

        if args.threads > 0:
            torch.set_num_threads(args.threads)
        cameras = json.loads(args.cameras) if args.cameras else None
        if cameras is not None and not (
            isinstance(cameras, dict) and all(isinstance(k, str) and isinstance(v, str) for k, v in cameras.items())
        ):
            raise ValueError(f"--cameras {args.cameras[:100]!r}: valid: a JSON object of image key -> camera name")
        server = LeRobotServer(
            args.path, device=args.device, suite=args.suite, trust_processors=args.trust_processors, cameras=cameras,
            n_action_steps=args.n_action_steps, full_chunk=args.full_chunk, rtc=rtc, rtc_prefix=args.rtc_prefix,
            empty_cameras=args.empty_cameras, relative_anchor=args.relative_anchor,
        )  # fmt: skip
    except Exception as exc:  # noqa: BLE001 - one line for the client to show
        print(f"error: cannot load a LeRobot policy from {args.path}: {type(exc).__name__}: {exc}", file=sys.stderr)
        return 2
    with contextlib.suppress(KeyboardInterrupt):
        serve(server, args.host, args.port, ready_out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
