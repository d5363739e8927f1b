"""Hostile policy servers, untrusted policy classes and secrets in results.

The servers here attack the client instead of failing (tests/standin_servers.py: HostileOpenPIServer,
RawHTTPServer), all on 127.0.0.1, each bounded in the time it takes and the bytes it sends:

- a reply that crashed the client process (openpi-client builds arrays of object dtype from the server's bytes);
- replies that never end (one byte per 0.9 s), that are huge (300 MiB announced, a 200 MiB websocket frame),
  or that redirect the request (and its camera images) elsewhere;
- ``package.module:Class`` names that are not policies (``subprocess:Popen``), and a policy node told to build
  a user's class by a runtime parameter change instead of by its launch;
- API keys and URL passwords that must never reach metadata, episode names, labels or sweep files, nor travel
  in clear to another machine.
"""

from __future__ import annotations

import base64
import hashlib
import json
import resource
import subprocess
import sys
import threading
import time
import tracemalloc
from pathlib import Path

import msgpack
import pandas as pd
import pytest

from lq_ros.core.redact import REDACTED, redact_args, strip_userinfo
from lq_ros.core.run_config import _KEY_OPTIONAL_FIELDS, PROVENANCE_FIELDS, RunConfig
from lq_ros.core.types import TaskInfo
from lq_ros.policies import PolicyError, make_policy
from lq_ros.policies.remote_wire import MAX_REPLY_BYTES, UnsafeReply, loads_json_numpy, unpack_msgpack_numpy
from lq_ros.recording.episode_bag import run_metadata
from lq_ros.run.validation import InputError, check_policy
from lq_ros.scoring.aggregate import label_variants
from tests.standin_servers import (
    HostileOpenPIServer,
    OpenPIStandin,
    OpenVLAStandin,
    RawHTTPServer,
    announce_and_stream,
    dripping_response,
    fixed_response,
    free_port,
    http_head,
    object_dtype_reply,
    send_bytes,
    standin_observation,
    streaming_response,
)

REPO = Path(__file__).resolve().parents[2]
TASK = TaskInfo("libero_spatial", 0, "t0", "pick up the black bowl", [], 220, 50)
MARKER_POLICY = "tests.policies.marker_policy:MarkerPolicy"
MIB = 2**20
SECRET = "sk-live-0123456789"


def no_core_dump() -> None:
    resource.setrlimit(resource.RLIMIT_CORE, (0, 0))


def run_python(code: str, *args: object, timeout_s: float = 60.0) -> subprocess.CompletedProcess:
    """``code`` in a fresh interpreter of this venv (repo root as working directory), no core file."""
    return subprocess.run(
        [sys.executable, "-c", code, *map(str, args)], cwd=REPO, capture_output=True, text=True,
        timeout=timeout_s, preexec_fn=no_core_dump,
    )  # fmt: skip


def infer_error(policy) -> tuple[str, float]:
    """The PolicyError text of one inference and how long it took (fails the test if there is no error)."""
    policy.reset(TASK, 7)
    started = time.monotonic()
    try:
        with pytest.raises(PolicyError) as err:
            policy.infer(standin_observation(256))
    finally:
        policy.close()
    return str(err.value), time.monotonic() - started


def one_line(text: str) -> None:
    assert "\n" not in text and "Traceback" not in text, text


# -- 1. replies decoded by our own hooks: plain numeric dtypes only --------------------------------------------
#: The client as a program of its own: exit 3 with the error line, 0 if the reply was accepted.
OPENPI_CLIENT = """
import sys
from lq_ros.policies import PolicyError, make_policy
from tests.policies.test_hostile_remote import TASK
from tests.standin_servers import standin_observation
policy = make_policy("openpi", port=int(sys.argv[1]), timeout_s=5.0)
policy.reset(TASK, 7)
try:
    policy.infer(standin_observation(256))
except PolicyError as exc:
    print(exc)
    sys.exit(3)
print("accepted")
"""
#: openpi-client's own decoder on the same reply, then what the client does with the actions.
OPENPI_CLIENT_DECODER = """
from openpi_client import msgpack_numpy
from lq_ros.policies.openpi_remote import checked_chunk
from tests.standin_servers import object_dtype_reply
print(checked_chunk(msgpack_numpy.unpackb(object_dtype_reply())["actions"], "server"))
"""


def test_object_dtype_reply_crashes_openpi_clients_own_decoder():
    """The control: the hostile reply is real (decoded as openpi-client does, the process dies of a signal)."""
    result = run_python(OPENPI_CLIENT_DECODER)
    assert result.returncode < 0, (result.returncode, result.stdout, result.stderr[-500:])


def test_object_dtype_reply_is_a_clean_one_line_error_not_a_crash():
    with HostileOpenPIServer(lambda server, ws: send_bytes(server, ws, object_dtype_reply())) as server:
        result = run_python(OPENPI_CLIENT, server.port)
    assert server.requests == 1
    assert result.returncode == 3, (result.returncode, result.stdout, result.stderr[-500:])  # no signal
    line = result.stdout.strip()
    one_line(line)
    assert "response refused: array dtype 'O' refused: only plain numeric dtypes" in line, line


def ndarray(data: bytes, dtype: object, shape: object) -> dict:
    return {b"__ndarray__": True, b"data": data, b"dtype": dtype, b"shape": shape}


@pytest.mark.parametrize(
    "dtype, data, shape, expected",
    [
        ("<f8", b"\0" * 56, [7], [0.0] * 7),
        ("|u1", b"\x01\x02", [2], [1, 2]),
        ("|b1", b"\x01\x00", [1, 2], [[True, False]]),
        ("<i4", b"\x05\0\0\0", [1], [5]),
        ("=f4", b"\0\0\x80\x3f", [1], [1.0]),
        ("<f2", b"\0\x3c", [], 1.0),
    ],
)
def test_plain_numeric_arrays_decode(dtype, data, shape, expected):
    decoded = unpack_msgpack_numpy(msgpack.packb({"a": ndarray(data, dtype, shape)}))["a"]
    assert decoded.tolist() == expected
    as_json = json.dumps({"__numpy__": base64.b64encode(data).decode(), "dtype": dtype, "shape": shape})
    assert loads_json_numpy(as_json).tolist() == expected


@pytest.mark.parametrize(
    "dtype, data, shape, message",
    [
        ("O", b"A" * 56, [7], "dtype 'O' refused"),
        ("|O", b"A" * 8, [1], "dtype '|O' refused"),
        (">f8", b"\0" * 8, [1], "dtype '>f8' refused"),
        ("<U4", b"\0" * 16, [1], "dtype '<U4' refused"),
        ("<M8[s]", b"\0" * 8, [1], "refused"),
        ("|V8", b"\0" * 8, [1], "refused"),
        ("<c16", b"\0" * 16, [1], "refused"),
        ([["a", "|O"]], b"A" * 8, [1], "refused"),  # a structured dtype with an object field (json-numpy's descr)
        ("<f8", b"\0" * 8, [7], "needs 56 bytes, the reply has 8"),
        ("<f8", b"\0" * 64, [7], "needs 56 bytes, the reply has 64"),
        ("<f8", b"\0" * 8, [-1], "shape [-1] refused"),
        ("<f8", b"\0" * 8, "8", "shape '8' refused"),
        ("<f8", b"\0" * 8, [1] * 40, "refused"),
    ],
)
def test_other_arrays_are_refused_with_one_line(dtype, data, shape, message):
    with pytest.raises(UnsafeReply, match=message.replace("[", r"\[").replace("]", r"\]")) as err:
        unpack_msgpack_numpy(msgpack.packb({"actions": [ndarray(data, dtype, shape)]}))
    one_line(str(err.value))
    as_json = json.dumps({"__numpy__": base64.b64encode(data).decode(), "dtype": dtype, "shape": shape})
    with pytest.raises(UnsafeReply):
        loads_json_numpy(as_json)


def test_numpy_scalars_must_be_numeric():
    scalar = {b"__npgeneric__": True, b"data": 2.5, b"dtype": "<f4"}
    assert float(unpack_msgpack_numpy(msgpack.packb(scalar))) == 2.5
    with pytest.raises(UnsafeReply, match="dtype 'O' refused"):
        unpack_msgpack_numpy(msgpack.packb({**scalar, b"dtype": "O"}))
    with pytest.raises(UnsafeReply, match="not a number"):
        unpack_msgpack_numpy(msgpack.packb({**scalar, b"data": "2.5"}))


@pytest.mark.parametrize("oft_list", [False, True])
def test_openvla_object_dtype_reply_is_refused(oft_list):
    hostile = {"__numpy__": base64.b64encode(b"A" * 56).decode(), "dtype": "|O", "shape": [7]}
    body = json.dumps([hostile, hostile] if oft_list else hostile).encode()
    reply = http_head(Content_Type="application/json", Content_Length=len(body)) + body
    with RawHTTPServer(fixed_response(reply)) as server:
        message, _ = infer_error(make_policy("openvla", url=server.url, timeout_s=5.0))
    one_line(message)
    assert f"OpenVLA server {server.url}: response refused: array dtype '|O' refused" in message


# -- 2. package.module:Class is trusted input, and only a Policy class is ever called ---------------------------
def test_a_callable_that_is_not_a_policy_class_is_never_called(tmp_path):
    marker = tmp_path / "X"
    for name, args in (
        ("subprocess:Popen", {"args": ["touch", str(marker)]}),
        ("tests.policies.marker_policy:not_a_policy", {"marker": str(marker)}),
        ("os:system", {"command": f"touch {marker}"}),
    ):
        with pytest.raises(InputError) as err:
            check_policy(name, args)
        one_line(str(err.value))
        assert "lq_ros.policies.base.Policy" in str(err.value)
        with pytest.raises(ValueError, match="not a Policy class"):
            make_policy(name, **args)
    assert not marker.exists()
    check_policy(MARKER_POLICY, {"marker": str(marker)})  # a user's own Policy subclass: built (and closed)
    assert marker.read_text() == "constructed\n"


@pytest.mark.slow
@pytest.mark.ros
def test_policy_node_builds_a_module_class_only_as_launched(tmp_path):
    """Anyone in the ROS domain can set /lq_policy's parameters; a package.module:Class policy is still built only
    if the launching user chose it (the params file the node was started with), registry names stay switchable."""
    from lq_ros.transport.processes import die_with_parent
    from lq_ros.transport.ros.stack import NODE_MODULE, child_environment, params_yaml, reserved_domain
    from tests.transport.ros.test_lifecycle import LifecycleClient

    params = tmp_path / "params.yaml"
    from_runtime, from_launcher = tmp_path / "runtime_marker", tmp_path / "launcher_marker"

    def launcher_writes(cfg: RunConfig) -> None:  # as RosStack does before each episode
        params.write_text(params_yaml({"/**": cfg.ros_parameters()}))

    launcher_writes(RunConfig(policy="sine"))
    log_path = tmp_path / "policy.log"
    with reserved_domain() as domain:
        env = child_environment(domain.id, tmp_path / "ros_logs")
        with open(log_path, "wb") as log:
            proc = subprocess.Popen(
                [sys.executable, "-m", NODE_MODULE.format("policy"), "--ros-args", "--params-file", str(params)],
                env=env, cwd=REPO, stdout=log, stderr=subprocess.STDOUT, preexec_fn=die_with_parent,
                pass_fds=(domain.lock_fd,),
            )  # fmt: skip
        client = LifecycleClient(domain.id, "lq_policy")
        try:
            assert client.state() == "unconfigured"
            # A participant of the domain asks for a user's class: refused at configure, never constructed.
            assert client.set_param("policy", MARKER_POLICY) == (True, "")
            assert client.set_param("policy_args", json.dumps({"marker": str(from_runtime)})) == (True, "")
            assert not client.set_state("configure") and client.state() == "unconfigured"
            assert not from_runtime.exists()
            assert "set at runtime, not by the user who launched this node" in log_path.read_text()
            # Registry names remain switchable at runtime.
            assert client.set_param("policy", "scripted") == (True, "")
            assert client.set_param("policy_args", "{}") == (True, "")
            assert client.set_state("configure") and client.state() == "inactive"
            assert client.set_state("cleanup")
            # The launcher (the user) names the class in the node's params file: accepted.
            chosen = RunConfig(policy=MARKER_POLICY, policy_args={"marker": str(from_launcher)})
            launcher_writes(chosen)
            assert client.set_param("policy", MARKER_POLICY) == (True, "")
            assert client.set_param("policy_args", chosen.ros_parameters()["policy_args"]) == (True, "")
            assert client.set_state("configure") and from_launcher.exists()
            assert client.set_state("cleanup")
            # The same class with other arguments, set at runtime: refused.
            assert client.set_param("policy_args", json.dumps({"marker": str(from_runtime)})) == (True, "")
            assert not client.set_state("configure") and not from_runtime.exists()
            assert client.set_state("shutdown")
            assert proc.wait(timeout=30) == 0
        finally:
            client.close()
            if proc.poll() is None:
                proc.kill()
                proc.wait()


@pytest.mark.slow
@pytest.mark.sim
@pytest.mark.ros
def test_launcher_switches_between_module_class_policies_on_one_stack(tmp_path):
    """The launcher's own choices stay switchable: two package.module:Class variants, one long-lived stack."""
    from lq_ros.transport.ros.stack import RosStack

    sleepy = "lq_ros.policies.sleepy:SleepyPolicy"
    with RosStack() as stack:
        for k, args in enumerate(({"sleep_s": 0.0, "inner": "sine"}, {"sleep_s": 0.01, "inner": "sine"})):
            _, reason = stack.run_episode(RunConfig(policy=sleepy, policy_args=args, max_steps=6), tmp_path / str(k))
            assert reason == "", reason


# -- 6. limits: one deadline per request, a byte cap, no redirects --------------------------------------------
ANSWER = json.dumps([0.1, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0]).encode()  # a valid OpenVLA answer, if it ever arrived


@pytest.mark.parametrize("dripped", ["body", "headers"])
def test_openvla_timeout_covers_the_whole_response(dripped):
    """Each byte arrives within 0.9 s (a per-read timeout of 1 s never fires); the request still ends at 1 s."""
    head = http_head(Content_Type="application/json", Content_Length=len(ANSWER))
    status_line, rest = head.split(b"\r\n", 1)
    prefix, drip = (head, ANSWER) if dripped == "body" else (status_line + b"\r\n", rest + ANSWER)
    with RawHTTPServer(dripping_response(prefix, drip, period_s=0.9, max_s=4.0)) as server:
        message, elapsed_s = infer_error(make_policy("openvla", url=server.url, timeout_s=1.0))
    assert message == f"OpenVLA server {server.url}: no response within 1.0 s"
    assert 0.9 < elapsed_s < 1.8


def _peak_bytes_during(call) -> int:
    tracemalloc.start()
    try:
        call()
    finally:
        _, peak = tracemalloc.get_traced_memory()
        tracemalloc.stop()
    return peak


def _normal_openvla_peak() -> int:
    """Peak traced memory of one ordinary OpenVLA request (the image preprocessing dominates)."""
    reply = http_head(Content_Type="application/json", Content_Length=len(ANSWER)) + ANSWER
    with RawHTTPServer(fixed_response(reply)) as server:
        policy = make_policy("openvla", url=server.url, timeout_s=5.0)
        policy.reset(TASK, 7)
        peak = _peak_bytes_during(lambda: policy.infer(standin_observation(256)))
        policy.close()
    return peak


@pytest.mark.parametrize("chunked", [False, True])
def test_openvla_reply_over_the_cap_is_refused_early(chunked):
    """A reply announcing 300 MiB (or streaming without a length): the client stops at the cap, memory stays
    bounded, and the server never gets to send its (bounded) 40 MiB."""
    limit = 40 * MIB
    head = (
        http_head(Content_Type="application/json", Transfer_Encoding="chunked")
        if chunked
        else http_head(Content_Type="application/json", Content_Length=300 * MIB)
    )
    baseline = _normal_openvla_peak()
    messages: list[str] = []
    with RawHTTPServer(streaming_response(head, limit, chunked=chunked)) as server:
        policy = make_policy("openvla", url=server.url, timeout_s=10.0)
        peak = _peak_bytes_during(lambda: messages.append(infer_error(policy)[0]))
        assert server.wait_responded()  # the client hung up (or the server sent all it would)
    (message,) = messages
    one_line(message)
    if chunked:
        assert "response refused: reply exceeds the 16 MiB limit" in message
        assert peak < baseline + MAX_REPLY_BYTES + 2 * MIB  # what was kept, never the 40 MiB
    else:
        assert f"response refused: Content-Length {300 * MIB} exceeds the 16 MiB limit" in message
        assert peak < baseline + 2 * MIB  # refused from the header: nothing of the body is kept
    assert server.sent_bytes < limit


def test_openvla_redirect_is_an_error_never_followed():
    with OpenVLAStandin() as elsewhere:
        redirect = http_head("307 Temporary Redirect", Location=elsewhere.url, Content_Length=0)
        with RawHTTPServer(fixed_response(redirect)) as server:
            message, _ = infer_error(make_policy("openvla", url=server.url, timeout_s=5.0))
    assert message == (
        f"OpenVLA server {server.url}: HTTP 307 redirect to {elsewhere.url!r} refused (redirects are not followed: "
        "give the final address as url)"
    )
    assert elsewhere.requests == 0  # the image never went there


def test_openpi_redirect_is_an_error_never_followed():
    from websockets.sync.server import serve

    with OpenPIStandin() as elsewhere:
        target = f"ws://127.0.0.1:{elsewhere.port}"

        def redirect(connection, request):
            response = connection.respond(307, "")
            response.headers["Location"] = target
            return response

        server = serve(lambda ws: None, "127.0.0.1", 0, process_request=redirect)
        thread = threading.Thread(target=server.serve_forever, daemon=True)
        thread.start()
        try:
            port = server.socket.getsockname()[1]
            message, _ = infer_error(make_policy("openpi", port=port, timeout_s=5.0))
        finally:
            server.shutdown()
            thread.join(timeout=5)
    assert message == (
        f"openpi server ws://127.0.0.1:{port}: HTTP 307 redirect to {target!r} refused (redirects are not followed: "
        "give the final address as host)"
    )
    assert elsewhere.connections == 0


def test_openpi_frame_over_the_cap_is_refused_from_its_header():
    """A frame announcing 200 MiB (32 MiB of it actually sent at most): refused before its payload is read."""
    limit = 32 * MIB
    messages: list[str] = []
    with HostileOpenPIServer(announce_and_stream(200 * MIB, limit)) as server:
        policy = make_policy("openpi", port=server.port, timeout_s=10.0)
        started = time.monotonic()
        peak = _peak_bytes_during(lambda: messages.append(infer_error(policy)[0]))
        elapsed_s = time.monotonic() - started
        assert server.handled.wait(10.0)  # the client hung up (or the server sent all it would)
    (message,) = messages
    one_line(message)
    assert message.startswith(f"openpi server ws://127.0.0.1:{server.port}: response refused: larger than the 16 MiB")
    assert f"{200 * MIB} bytes" in message
    assert peak < 4 * MIB and elapsed_s < 5.0
    assert server.requests == 1 and server.sent_bytes < limit


# -- 7. secrets never reach results; never sent in clear ---------------------------------------------------
def test_redact_args():
    args = {
        "api_key": SECRET, "token": "t0k", "Password": "pw", "client_secret": "s", "authorization": "Bearer x",
        "host": "wss://user:pw@gpu.example:8000/path", "url": "http://gpu.example/act", "port": 8000,
        "max_tokens": 256, "api_key_file": None, "nested": {"auth": "a", "urls": ["https://u:p@h/x"]}, "empty": "",
    }  # fmt: skip
    assert redact_args(args) == {
        "api_key": REDACTED, "token": REDACTED, "Password": REDACTED, "client_secret": REDACTED,
        "authorization": REDACTED, "host": "wss://gpu.example:8000/path", "url": "http://gpu.example/act",
        "port": 8000, "max_tokens": 256, "api_key_file": None, "nested": {"auth": REDACTED, "urls": ["https://h/x"]},
        "empty": "",
    }  # fmt: skip
    plain = {"port": 8000, "style": "oft", "unnorm_key": "libero_spatial", "host": "ws://gpu:1", "weights": "/w.pt"}
    assert redact_args(plain) == plain
    assert strip_userinfo("no url@all") == "no url@all"


def _old_key(cfg: RunConfig) -> str:
    """RunConfig.key() as computed before redaction existed (and before provenance fields, which no key holds)."""
    fields = {
        k: v
        for k, v in cfg.to_dict().items()
        if _KEY_OPTIONAL_FIELDS.get(k, object()) != v and k not in PROVENANCE_FIELDS
    }
    return hashlib.sha256(json.dumps(fields, sort_keys=True).encode()).hexdigest()[:12]


def test_keys_and_names_of_configurations_without_secrets_are_unchanged():
    for cfg in (
        RunConfig(),
        RunConfig(policy="openpi", policy_args={"port": 8000, "host": "ws://gpu:8000", "timeout_s": 5.0}),
        RunConfig(policy="openvla", policy_args={"url": "http://gpu:8777/act", "style": "oft", "unnorm_key": "x"}),
        RunConfig(policy=MARKER_POLICY, policy_args={"marker": "/tmp/m", "max_tokens": 3}, mode="async"),
    ):
        assert cfg.key() == _old_key(cfg)
    with_secret = RunConfig(policy="openpi", policy_args={"api_key": SECRET, "host": "wss://u:pw@gpu"})
    other_secret = RunConfig(policy="openpi", policy_args={"api_key": "other", "host": "wss://v:xx@gpu"})
    assert with_secret.key() == other_secret.key() != _old_key(with_secret)  # the secret is not hashed either


def test_no_secret_in_run_metadata_episode_name_labels_or_messages():
    args = {"host": "wss://user:hunter2@gpu.example", "port": 8443, "api_key": SECRET}
    cfg = RunConfig(policy="openpi", policy_args=args)
    policy = make_policy(cfg.policy, **cfg.policy_args)
    meta = json.dumps(run_metadata(cfg, policy.params(), "inprocess", {}, 256))
    assert SECRET not in meta and "hunter2" not in meta and "wss://gpu.example:8443" in meta
    assert SECRET not in cfg.episode_name() and "hunter2" not in cfg.episode_name()
    # A score row of a bag written before redaction existed still gets a clean label.
    row = {"policy": "openpi", "policy_args": json.dumps(args), "mode": "sync", "latency_s": 0.0}
    label = label_variants(pd.DataFrame([row]))["policy"][0]
    assert label == "openpi [api_key=***, host=wss://gpu.example, port=8443]"
    # Error messages name the server without its password.
    down = make_policy("openpi", host="ws://user:hunter2@127.0.0.1", port=free_port(), timeout_s=1.0)
    message, _ = infer_error(down)
    assert "unreachable" in message and "hunter2" not in message
    with pytest.raises(InputError) as err:
        check_policy("openpi", {"api_key": SECRET, "timeout_s": -1})
    assert "api_key='***'" in str(err.value) and SECRET not in str(err.value)


def test_sweep_files_carry_no_secret(tmp_path):
    from lq_ros.run.sweep.orchestrator import prepare
    from lq_ros.run.sweep.spec import expand_spec

    raw = {
        "name": "secrets", "transport": "inprocess", "suites": {"libero_spatial": {"tasks": [0], "inits": [0]}},
        "seeds": [7], "latencies_s": [0.0], "modes": {"sync": {"replan_steps": 5}},
        "policies": [{"name": "openpi", "args": {"host": "wss://user:hunter2@gpu.example", "api_key": SECRET}}],
    }  # fmt: skip
    spec = expand_spec(raw)
    prepare(spec, tmp_path)
    for path in tmp_path.rglob("*"):
        if path.is_file():
            text = path.read_text(errors="replace")
            assert SECRET not in text and "hunter2" not in text, path
    assert spec.configs[0].policy_args["api_key"] == SECRET  # the run itself still has its key
    malformed = {**raw, "policies": [{"name": "openpi", "args": {"api_key": SECRET}, "typo": 1}]}
    with pytest.raises(ValueError, match="expected a policy name") as err:
        expand_spec(malformed)
    assert SECRET not in str(err.value)


@pytest.mark.parametrize(
    "kind, args, refused",
    [
        ("openpi", {"host": "gpu.example", "api_key": SECRET}, "an API key would be sent unencrypted (ws://)"),
        ("openpi", {"host": "ws://u:pw@10.0.0.5"}, "a URL password would be sent unencrypted (ws://)"),
        ("openpi", {"host": "gpu.example", "api_key": SECRET, "allow_insecure": True}, None),
        ("openpi", {"host": "wss://gpu.example", "api_key": SECRET}, None),
        ("openpi", {"host": "localhost", "api_key": SECRET}, None),
        ("openpi", {"host": "ws://[::1]", "api_key": SECRET}, None),
        ("openvla", {"url": "http://u:pw@gpu.example:8000/act"}, "a URL password would be sent unencrypted (http://)"),
        ("openvla", {"url": "https://u:pw@gpu.example/act"}, None),
        ("openvla", {"url": "http://u:pw@gpu.example/act", "allow_insecure": True}, None),
    ],
)
def test_credentials_never_travel_in_clear_to_another_host(monkeypatch, kind, args, refused):
    monkeypatch.delenv("OPENPI_API_KEY", raising=False)
    if refused is None:
        make_policy(kind, **args).close()
        check_policy(kind, args)
        return
    with pytest.raises(InputError) as err:
        check_policy(kind, args)
    one_line(str(err.value))
    assert refused in str(err.value) and "allow_insecure=true" in str(err.value)
    assert SECRET not in str(err.value) and "pw@" not in str(err.value)


def test_api_key_from_the_environment_is_not_sent_in_clear_either(monkeypatch):
    monkeypatch.setenv("OPENPI_API_KEY", SECRET)
    with pytest.raises(ValueError, match="an API key would be sent unencrypted"):
        make_policy("openpi", host="10.0.0.5")
    make_policy("openpi").close()  # the default host is loopback


def test_openvla_url_user_info_is_sent_as_basic_auth():
    reply = http_head(Content_Type="application/json", Content_Length=len(ANSWER)) + ANSWER
    with RawHTTPServer(fixed_response(reply)) as server:
        policy = make_policy("openvla", url=f"http://us%40er:p%3Aw@127.0.0.1:{server.port}/act", timeout_s=5.0)
        policy.reset(TASK, 7)
        chunk = policy.infer(standin_observation(256))
        policy.close()
    assert chunk.shape == (1, 7) and policy.url == server.url
    assert f"Authorization: Basic {base64.b64encode(b'us@er:p:w').decode()}".encode() in server.heads[0]
