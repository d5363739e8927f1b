"""pi0 and pi0.5 of LeRobot 0.6 (``make setup-lerobot06``), built offline at tiny sizes and served like published ones.

``make test`` builds ``.venv-lerobot06``; run by hand without it, every test here is skipped, saying why (in CI a
missing venv fails).

LeRobot fixes pi0's and pi0.5's sizes in code, not in the checkpoint's config: ``get_gemma_config`` knows only
``gemma_2b`` and ``gemma_300m``, and ``PaliGemmaWithExpertModel`` builds transformers' default SigLIP tower (27
layers, 1152 wide), a 2048-wide projection and a 257152-row vocabulary: about 4e9 parameters, 16 GB as float32.
So the helper script and the server run with a TEST-ONLY shim, ``pi_tiny_sizes/sitecustomize.py``, on
``PYTHONPATH`` (the server gets it through a two-line wrapper passed as ``python=``; the product never loads it).
It replaces sizes only: what the two variant names mean (64 and 32 wide, 2 layers), the vision tower's width,
depth, heads, MLP width and patch size, the projection (the language model's width) and the vocabulary (512 rows).
Every class, forward pass, processor and RTC step is LeRobot's; the configs name ``gemma_2b``/``gemma_300m`` as
LeRobot writes them. The processors name the hub tokenizer ``google/paligemma-3b-pt-224``: the helper makes a
word-level toy tokenizer, and the saved preprocessor's ``tokenizer_name`` points at its folder (no hub).
"""

from __future__ import annotations

import json
import shlex
from pathlib import Path

import pytest

from lq_ros.core.run_config import RunConfig
from lq_ros.core.types import TaskInfo
from lq_ros.policies import make_policy
from lq_ros.policies.lerobot_client import RTC_TYPES, check_config, check_processor_steps
from lq_ros.recording.bag_compare import bag_messages
from lq_ros.run.episode import run_episode
from lq_ros.wire import messages as m
from tests.policies.rtc_check import check_rtc_follows_the_prefix
from tests.policies.test_lerobot06 import python06, run_in_venv06
from tests.policies.venv_jobs import ModuleServers

HERE = Path(__file__).parent
SCRIPT = HERE / "lerobot_pi_script.py"
SHIM = HERE / "pi_tiny_sizes"
TASK_INFO = TaskInfo("libero_spatial", 0, "t", "pick up the black bowl", [], 220, 50)
SOURCE_CHUNK = 0  # ActionCommand.SOURCE_CHUNK
CHUNK, STEPS = 10, 5  # as lerobot_pi_script.py makes them
KINDS = ["pi0", "pi05"]

pytestmark = [pytest.mark.sim]


def in_venv06_with_shim(*args: object) -> dict:
    # the size shim; nothing may come from a hub
    return run_in_venv06(SCRIPT, *args, env={"PYTHONPATH": str(SHIM), "HF_HUB_OFFLINE": "1"})


@pytest.fixture(scope="module")
def made(tmp_path_factory) -> dict:
    """The checkpoints (and what our server loads of each, checked in the same process), and a wrapper Python that
    starts LeRobot 0.6's venv with the size shim, offline."""
    out = tmp_path_factory.mktemp("lerobot06_pi")
    result = in_venv06_with_shim("make-and-check", out)
    wrapper = out / "python-with-tiny-pi-sizes"
    wrapper.write_text(
        f'#!/bin/sh\nPYTHONPATH={shlex.quote(str(SHIM))} HF_HUB_OFFLINE=1 exec {shlex.quote(str(python06()))} "$@"\n'
    )
    wrapper.chmod(0o755)
    return {**result, "python": str(wrapper)}


def policy_pi(made: dict, kind: str, **args):
    return make_policy("lerobot", path=made[kind], python=made["python"], threads=1, **args)


@pytest.fixture(scope="module")
def served(made):
    """One server per checkpoint (as policy_pi makes it) for this module's RTC checks and episodes."""
    servers = ModuleServers(lambda kind: policy_pi(made, kind))
    yield servers
    servers.close()


def chunk_rows(bag: Path) -> int:
    commands = [m.deserialize(raw, m.COMMAND.msgtype) for _, raw in bag_messages(bag).get(m.COMMAND.name, [])]
    return sum(c.source == SOURCE_CHUNK for c in commands)


def chunk_horizons(bag: Path) -> list[int]:
    chunks = bag_messages(bag).get(m.ACTION_CHUNK.name, [])
    return [m.deserialize(raw, m.ACTION_CHUNK.msgtype).horizon for _, raw in chunks]


@pytest.mark.parametrize("kind", KINDS)
def test_tiny_checkpoint_is_laid_out_as_lerobot_writes_it_and_loads_as_saved(made, kind):
    """The config keeps LeRobot's variant names and passes the client's checks; the server's policy holds the saved
    tensors (LeRobot's pi ``from_pretrained`` only prints a warning and keeps random weights when they do not fit)."""
    folder = Path(made[kind])
    config = check_config(folder / "config.json", kind)
    check_processor_steps(folder, kind)
    assert config["type"] == kind and kind in RTC_TYPES
    assert (config["paligemma_variant"], config["action_expert_variant"]) == ("gemma_2b", "gemma_300m")
    assert config["lq_cameras"] == {"observation.images.image": "image", "observation.images.image2": "image2"}
    steps = json.loads((folder / "policy_preprocessor.json").read_text())["steps"]
    names = [step["config"].get("tokenizer_name") for step in steps if step["registry_name"] == "tokenizer_processor"]
    assert names == [str(folder.parent / "toy_paligemma_tokenizer")]
    assert made["parameters"][kind] < 1_000_000  # tiny: the shim took effect when it was built
    loaded = made["loaded"][kind]
    assert loaded["same"] and loaded["type"] == kind, loaded


@pytest.mark.parametrize("kind", KINDS)
def test_rtc_guided_chunk_follows_the_prefix(served, kind):
    """The executor's prefix and delay reach LeRobot's RTC processor in pi0 and pi0.5 (tests/policies/rtc_check.py),
    and the server is the policy asked for."""
    policy = served(kind)
    check_rtc_follows_the_prefix(policy, TASK_INFO, CHUNK, STEPS)
    assert policy.server_metadata["policy_type"] == kind and policy.server_metadata["lerobot_version"] == "0.6.1"


@pytest.mark.slow
@pytest.mark.parametrize("kind", KINDS)
def test_async_episode_with_rtc(made, served, kind, tmp_path):
    """Every request of the episode went through LeRobot's RTC: each answer is the whole chunk of
    ``predict_action_chunk`` (10 rows); a request without a prefix gets select_action's 5. On the module's server of
    the checkpoint, as a sweep reuses a policy (the episode resets it)."""
    cfg = RunConfig(
        suite="libero_spatial", task=0, init=1, seed=3, mode="async", latency_s=0.1, merge="rtc", policy="lerobot",
        policy_args={"path": made[kind], "python": made["python"], "threads": 1}, max_steps=30,
    )  # fmt: skip
    outcome, row = run_episode(cfg, tmp_path / kind, "inprocess", policy=served(kind))
    assert outcome.status == row["status"] == "failure", (outcome, row.get("error_reason"))
    assert chunk_rows(outcome.bag_path) > 0
    horizons = chunk_horizons(outcome.bag_path)
    assert len(horizons) >= 3 and set(horizons) == {CHUNK}, horizons
    assert row["latency_real_mean_s"] > 0 and row["merge"] == "rtc"
