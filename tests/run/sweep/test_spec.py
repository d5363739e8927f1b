"""Sweep specs: expansion to episodes, validation with clear messages, policy arguments checked up front."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from lq_ros.run import sweep as sw

REPO = Path(__file__).resolve().parents[3]


def small_spec(**over) -> dict:
    spec = {
        "name": "small",
        "transport": "inprocess",
        "suite": "libero_spatial",
        "tasks": [0],
        "inits": [0],
        "policies": ["sine"],
        "latencies_s": [0.0, 0.1],
        "modes": ["sync", "async"],
        "max_steps": 8,
    }
    spec.update(over)
    return spec


def test_expansion_is_the_full_product_in_a_stable_order():
    raw = {
        "suites": {"libero_spatial": {"tasks": [0, 3], "inits": [0, 1]}},
        "seeds": [7, 8],
        "policies": ["sine", {"name": "scripted", "args": {}}],
        "latencies_s": [0, 0.1, 0.2, 0.4],
        "modes": {
            "sync": {"replan_steps": [4, 8], "hold": "stop"},
            "async": {"request_threshold": 9, "merge": ["replace", "weighted_average"]},
        },
        "max_steps": 30,
    }
    spec = sw.expand_spec(raw)
    # policies 2 x protocol variants (2 sync + 2 async) x latencies 4 x tasks 2 x inits 2 x seeds 2
    assert len(spec.configs) == 2 * 4 * 4 * 2 * 2 * 2
    assert len({c.key() for c in spec.configs}) == len(spec.configs)
    assert {c.replan_steps for c in spec.configs if c.mode == "sync"} == {4, 8}
    assert {c.merge for c in spec.configs if c.mode == "async"} == {"replace", "weighted_average"}
    assert all(c.max_steps == 30 for c in spec.configs)
    assert [c.key() for c in sw.expand_spec(raw).configs] == [c.key() for c in spec.configs]


def test_latencies_between_ticks_and_merges_without_overlap_are_refused():
    base = {"tasks": [0], "inits": [0], "policies": ["sine"]}
    with pytest.raises(sw.SpecError, match=r"latencies_s: latency 0.075 s .* nearest valid: 0.05 s or 0.1 s"):
        sw.expand_spec(base | {"latencies_s": [0.075]})
    rounded = sw.expand_spec(base | {"latencies_s": [0.075, 0.2], "latency_rounding": "nearest"})
    assert sorted({c.latency_s for c in rounded.configs}) == [0.05, 0.2]
    with pytest.raises(sw.SpecError, match="never sees overlapping chunks"):
        sw.expand_spec(base | {"latencies_s": [0.2], "modes": {"async": {"merge": "average", "request_threshold": 4}}})


def test_latency_distributions_in_a_spec():
    base = {"tasks": [0], "inits": [0], "policies": ["sine"], "modes": {"async": {"merge": ["replace", "rtc"]}}}
    spec = sw.expand_spec(base | {"latencies_s": [0.2, "uniform:0.075:0.275", "lognormal:0.2:0.5"]})
    assert len(spec.configs) == 2 * 3
    assert {c.latency_dist for c in spec.configs} == {"", "uniform:0.075:0.275", "lognormal:0.2:0.5"}
    assert {c.latency_s for c in spec.configs if c.latency_dist.startswith("uniform")} == {0.2}  # applied mean
    sw.check_policies(spec.configs)  # sine inpaints a prefix in closed form: rtc is fine
    with pytest.raises(sw.SpecError, match="listed twice"):
        sw.expand_spec(base | {"latencies_s": ["uniform:0.1:0.3", "uniform:0.1:0.30"]})
    with pytest.raises(sw.SpecError, match="unknown distribution 'gamma'"):
        sw.expand_spec(base | {"latencies_s": ["gamma:1:2"]})


def test_rtc_with_a_policy_that_takes_no_prefix_is_refused_before_running():
    spec = sw.expand_spec(
        {
            "tasks": [0],
            "inits": [0],
            "policies": ["scripted"],
            "latencies_s": [0.1],
            "modes": {"async": {"merge": "rtc"}},
        }
    )
    with pytest.raises(sw.SpecError, match="merge 'rtc' .* policy 'scripted' cannot"):
        sw.check_policies(spec.configs)


def test_tasks_all_and_shorthand_and_defaults():
    spec = sw.expand_spec({"tasks": "all", "inits": [0], "policies": ["sine"], "latencies_s": [0.0]})
    assert sorted({c.task for c in spec.configs}) == list(range(10))
    assert {c.mode for c in spec.configs} == {"sync", "async"} and {c.seed for c in spec.configs} == {7}
    assert spec.transport is None and spec.name == "sweep"


def test_parts_join_several_products_in_one_sweep():
    """Each part is the top level with its own keys over it (here: the top level's init state 0 in both parts)."""
    raw = small_spec(
        parts=[
            {},  # the top level as it is: 1 policy x 2 latencies x 2 modes x task 0
            {"suite": "libero_object", "tasks": [1, 2], "policies": ["scripted"], "modes": ["async"]},
        ]
    )
    spec = sw.expand_spec(raw)
    assert sw.spec.count_episodes(raw) == len(spec.configs) == 4 + 1 * 2 * 1 * 2
    first, second = spec.configs[:4], spec.configs[4:]
    assert {(c.suite, c.task, c.policy) for c in first} == {("libero_spatial", 0, "sine")}
    assert {(c.suite, c.task, c.policy, c.mode) for c in second} == {
        ("libero_object", 1, "scripted", "async"), ("libero_object", 2, "scripted", "async")}  # fmt: skip
    assert all(c.max_steps == 8 for c in spec.configs)  # the top level's, in both parts
    assert [c.key() for c in sw.expand_spec(raw).configs] == [c.key() for c in spec.configs]


@pytest.mark.parametrize(
    "parts, message",
    [
        ([], "parts: expected a list of 1..64 mappings"),
        ("all", "parts: expected a list"),
        ([{}, 3], "parts[1]: expected a mapping"),
        ([{"transport": "ros"}], "parts[0]: ['transport'] apply to the whole sweep"),
        ([{"latencies": [0.1]}], "parts[0]: unknown key(s) ['latencies']"),
        ([{"tasks": [12]}], "parts[0]: suites.libero_spatial.tasks"),
        ([{"suites": {"libero_goal": {"tasks": [0]}}}], "parts[0]: suites.libero_goal: 'tasks'"),
        ([{}, {"modes": ["sync"]}], "parts[1]: the spec lists the same episode twice"),
    ],
)
def test_bad_parts_are_refused_naming_the_part(parts, message):
    with pytest.raises(sw.SpecError) as info:
        sw.expand_spec(small_spec(parts=parts))
    assert message in str(info.value)


@pytest.mark.parametrize(
    "change, message",
    [
        ({"latencies": [0.1]}, "unknown key"),
        ({"policies": ["nope"]}, "unknown policy 'nope'"),
        ({"policies": [{"name": "sine", "arg": {}}]}, "policies[0]"),
        ({"latencies_s": [0.1, 0.1]}, "are both N = 2"),
        ({"latencies_s": [0.12]}, "not a whole number of 0.05 s control ticks"),
        ({"latencies_s": [-0.1]}, "non-negative"),
        ({"latencies_s": []}, "empty list"),
        ({"modes": ["sync", "stream"]}, "unknown mode 'stream'"),
        ({"modes": {"sync": {"chunk": 3}}}, "modes.sync"),
        ({"modes": {"sync": {"hold": "freeze"}}}, "hold"),
        ({"tasks": [10]}, "outside 0..9"),
        ({"inits": [50]}, "outside 0..49"),
        ({"suite": "libero_100"}, "unknown suite"),
        ({"transport": "zmq"}, "transport"),
        ({"max_steps": -1}, "max_steps"),
        ({"physics_rate": "yes"}, "physics_rate: expected bool"),
        ({"suites": {"libero_spatial": {"tasks": [0], "inits": [0]}}}, "not both"),
        ({"policies": ["sine", "sine"]}, "same episode twice"),
    ],
)
def test_invalid_specs_fail_with_a_clear_message(change, message):
    with pytest.raises(sw.SpecError, match=None) as info:
        sw.expand_spec(small_spec(**change))
    assert message in str(info.value)


def test_load_spec_names_the_file(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("policies: [sine\n")
    with pytest.raises(sw.SpecError, match="bad.yaml: not valid YAML"):
        sw.load_spec(bad)
    with pytest.raises(sw.SpecError, match="missing.yaml: cannot read"):
        sw.load_spec(tmp_path / "missing.yaml")
    good = tmp_path / "mine.yaml"
    good.write_text(yaml.safe_dump({k: v for k, v in small_spec().items() if k != "name"}))
    assert sw.load_spec(good).name == "mine"


def test_policy_arguments_are_checked_before_running():
    spec = sw.expand_spec(small_spec(policies=[{"name": "sine", "args": {"amplitude": 3.0}}]))
    with pytest.raises(sw.SpecError, match="amplitude must be in"):
        sw.check_policies(spec.configs)


def test_shipped_demo_spec_is_valid():
    spec = sw.load_spec(REPO / "config" / "sweeps" / "demo.yaml")
    assert spec.transport == "inprocess"
    assert {c.latency_s for c in spec.configs} == {0.0, 0.1, 0.2, 0.4}
    assert {c.mode for c in spec.configs} == {"sync", "async"}
    assert {c.init for c in spec.configs} == {0, 1}
    object_part = [c for c in spec.configs if c.suite == "libero_object"]
    assert {c.policy_args.get("variant", "naive") for c in object_part} == {"naive", "delay"}  # the contrast
    assert {c.mode for c in object_part} == {"async"}
    sw.check_policies(spec.configs)


def test_clock_and_robot_keys():
    spec = sw.expand_spec(small_spec(transport="ros", clock="realtime", robot="standin", latencies_s=[0.1]))
    assert {(c.clock, c.robot) for c in spec.configs} == {("realtime", "standin")}
    assert all("_realtime_standin_" in c.episode_name() for c in spec.configs)
    lockstep = sw.expand_spec(small_spec(clock="lockstep"))
    assert {c.clock for c in lockstep.configs} == {"lockstep"}
    assert lockstep.configs == sw.expand_spec(small_spec()).configs  # the default: nothing changes
    for over, message in [
        ({"clock": "wall"}, "clock: expected one of lockstep, realtime, got 'wall'"),
        ({"transport": "inprocess", "clock": "realtime"}, "clock: realtime runs through ROS only"),
        ({"transport": "ros", "robot": "standin"}, "robot: a robot runs on wall-clock time"),
        ({"transport": "ros", "clock": "realtime", "robot": "no_such_robot"}, "robot: "),
        ({"transport": "ros", "clock": "realtime", "robot": 3}, "robot: expected a robot YAML"),
    ]:
        with pytest.raises(sw.SpecError, match=message):
            sw.expand_spec(small_spec(**over))


def test_analysis_declares_primaries_and_an_equivalence_margin():
    raw = small_spec(policies=["sine", "scripted"],
                     analysis={"primary": [{"a": "sine", "b": "scripted", "mode": "async", "latency_s": 0.1}],
                               "equivalence_margin": 0.1})  # fmt: skip
    assert len(sw.expand_spec(raw).configs) == 8  # the analysis adds no episode
    for analysis, message in (
        ({"primary": [{"a": "sine", "b": "sine", "mode": "async"}]}, "compares 'sine' with itself"),
        ({"primary": [{"a": "flow", "b": "sine"}]}, "names no policy of the spec"),
        ({"equivalence_margin": -1}, "equivalence_margin"),
        ({"primaries": []}, "analysis: expected a mapping"),
    ):
        with pytest.raises(sw.SpecError, match=message):
            sw.expand_spec(small_spec(policies=["sine", "scripted"], analysis=analysis))
    with pytest.raises(sw.SpecError, match="apply to the whole sweep"):
        sw.expand_spec(small_spec(parts=[{"analysis": {}}]))


def test_sync_replan_steps_default_to_the_policys_declaration_and_a_given_one_wins():
    declared = sw.expand_spec(small_spec(modes=["sync"], latencies_s=[0.0])).configs
    assert [(c.replan_steps, c.replan_steps_source) for c in declared] == [(5, "policy")]
    given = sw.expand_spec(small_spec(modes={"sync": {"replan_steps": 8}}, latencies_s=[0.0])).configs
    assert [(c.replan_steps, c.replan_steps_source) for c in given] == [(8, "flag")]
    asynchronous = sw.expand_spec(small_spec(modes=["async"], latencies_s=[0.0])).configs
    assert [c.replan_steps_source for c in asynchronous] == [""]  # async executes no fixed count


def test_a_second_seed_for_a_seed_blind_policy_is_refused():
    """The bad case: the scripted expert ignores its seed and the init state is set after seeding, so seeds 7 and 8
    give one episode twice (benchmarks/seed_replication.py); counted as two it would double every count."""
    for policy in ("scripted", "sine"):
        spec = sw.expand_spec(small_spec(policies=[policy], seeds=[7, 8]))
        with pytest.raises(sw.SpecError, match=f"seeds: \\[7, 8\\] for policy '{policy}', whose episodes do not"):
            sw.check_policies(spec.configs)
    sw.check_policies(sw.expand_spec(small_spec(policies=["scripted"], seeds=[7])).configs)  # one seed: fine
