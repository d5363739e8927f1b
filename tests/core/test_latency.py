"""Latency distributions (lq_ros/core/latency.py): syntax, draws, rounding, reproducibility, applied means;
bounds (0..10 s, checked once), a file read once."""

import math
import re

import numpy as np
import pytest

from lq_ros.core.executor_protocol import ChunkDue, ExecutorConfig, ExecutorCore, ObservationNeeded
from lq_ros.core.latency import (
    MAX_LATENCY_S,
    LatencyError,
    applied_seconds,
    label_of,
    latency_stream,
    parse_latency,
    request_latency,
    ticks_of_draw,
)
from lq_ros.core.run_config import RunConfig


def test_ticks_of_a_draw_round_up_to_the_next_tick_boundary():
    assert [ticks_of_draw(x) for x in (0.0, 0.001, 0.05, 0.0500001, 0.1, 0.12, 0.15, 0.3)] == [0, 1, 1, 2, 2, 3, 3, 6]
    assert ticks_of_draw(3 * 0.05) == 3  # 0.15000000000000002 is on the boundary, not past it
    assert applied_seconds(3) == 0.15
    with pytest.raises(LatencyError):
        ticks_of_draw(-0.01)


@pytest.mark.parametrize(
    "text, kind, label",
    [
        ("0.2", "constant", "constant"),
        ("uniform:0.075:0.275", "uniform", "uniform:0.075:0.275"),
        ("normal:0.2:0.05", "normal", "normal:0.2:0.05"),
        ("lognormal:0.15:0.5", "lognormal", "lognormal:0.15:0.5"),
    ],
)
def test_parse_and_canonical_text(text, kind, label):
    dist = parse_latency(text)
    assert dist.kind == kind and dist.label == label and parse_latency(dist.text) == dist
    assert parse_latency(0.2) == parse_latency("0.2")


@pytest.mark.parametrize(
    "text, fragment",
    [
        ("0.075", "not a whole number of 0.05 s control ticks"),
        ("-0.1", "the constant latency -0.1 is outside 0..10 s"),
        ("gamma:1:2", "unknown distribution 'gamma'"),
        ("uniform:0.3:0.1", "0 <= LO <= HI"),
        ("uniform:0.1", "expected uniform:LO:HI"),
        ("normal:0.2:0", "STD > 0"),
        ("lognormal:0:1", "MEDIAN > 0"),
        ("uniform:a:0.2", "is not a number"),
        ("trace:/nonexistent/file.txt", "cannot read"),
    ],
)
def test_parse_errors_say_what_is_wrong(text, fragment):
    with pytest.raises(LatencyError, match=fragment):
        parse_latency(text)


@pytest.mark.parametrize("text", ["uniform:0.075:0.275", "normal:0.2:0.05", "lognormal:0.15:0.5"])
def test_draws_are_a_function_of_seed_and_request_id(text):
    dist = parse_latency(text)
    forward = [dist.draw_s(7, k) for k in range(1, 50)]
    backward = [dist.draw_s(7, k) for k in reversed(range(1, 50))][::-1]
    assert forward == backward  # no hidden state: the order of draws does not matter
    assert forward != [dist.draw_s(8, k) for k in range(1, 50)]  # the episode seed matters
    assert len(set(forward)) == len(forward)
    n, s = request_latency(text, 7, 3)
    assert n == ticks_of_draw(forward[2]) and s == applied_seconds(n)


def test_constant_latency_applies_the_configured_value():
    assert request_latency("0.15", 7, 1) == (3, 0.15)
    assert request_latency(parse_latency(0.2), 1, 99) == (4, 0.2)


def test_uniform_draws_and_exact_applied_mean():
    dist = parse_latency("uniform:0.075:0.275")
    draws = np.array([dist.draw_s(s, k) for s in range(40) for k in range(1, 251)])
    assert draws.min() >= 0.075 and draws.max() <= 0.275
    # ceil over [0.075, 0.275]: N = 2 (1/8), 3, 4, 5 (1/4 each), 6 (1/8) -> mean exactly 4 ticks.
    assert dist.mean_ticks() == 4.0 and dist.mean_s() == 0.2 and dist.nominal_ticks() == 4
    assert (dist.min_ticks(), dist.max_ticks()) == (2, 6)
    ticks = np.array([ticks_of_draw(x) for x in draws])
    assert abs(ticks.mean() - 4.0) < 0.05
    assert parse_latency("uniform:0.1:0.3").mean_ticks() == 4.5  # raw mean 0.2 s, applied 0.225 s


def test_normal_is_truncated_not_clipped():
    dist = parse_latency("normal:0:0.1")  # half-normal: mean 0.1 sqrt(2/pi)
    draws = np.array([dist.draw_s(s, k) for s in range(20) for k in range(1, 501)])
    assert draws.min() >= 0 and (draws == 0).sum() == 0  # clipping would put half the mass at 0
    assert abs(draws.mean() - 0.1 * math.sqrt(2 / math.pi)) < 0.003
    ticks = np.array([ticks_of_draw(x) for x in draws])
    assert abs(ticks.mean() - dist.mean_ticks()) < 0.05


def test_lognormal_median_and_applied_mean():
    dist = parse_latency("lognormal:0.15:0.5")
    draws = np.array([dist.draw_s(s, k) for s in range(20) for k in range(1, 501)])
    assert abs(np.median(draws) - 0.15) < 0.005
    assert abs(np.mean([ticks_of_draw(x) for x in draws]) - dist.mean_ticks()) < 0.06
    assert dist.min_ticks() == 0 and dist.max_ticks() is None


def test_trace_replays_in_order_wraps_and_pins_its_content(tmp_path):
    path = tmp_path / "server.txt"
    path.write_text("# measured Δt_real of a policy server, s\n0.087\n0.12\n\n0.31  # a slow one\n")
    dist = parse_latency(f"trace:{path}")
    assert dist.trace == (0.087, 0.12, 0.31) and dist.label == "trace:server.txt"
    ticks = [2, 3, 7]  # the lines' N, in file order
    for stream in [latency_stream(s, "libero_spatial", t, i) for s in (1, 2) for t in range(3) for i in range(3)]:
        offset = dist.trace_offset(stream)
        # Replayed in order from the episode's seeded offset, wrapped.
        assert [dist.ticks(stream, k) for k in range(1, 8)] == [ticks[(offset + k - 1) % 3] for k in range(1, 8)]
    offsets = {dist.trace_offset(latency_stream(7, "libero_spatial", t, i)) for t in range(5) for i in range(2)}
    assert offsets == {0, 1, 2}  # the ten episodes of one cell do not all start on the same line
    assert dist.mean_ticks() == 4.0 and (dist.min_ticks(), dist.max_ticks()) == (2, 7)
    assert "@sha256:" in dist.text and parse_latency(dist.text) == dist
    path.write_text("0.2\n")
    with pytest.raises(LatencyError, match="changed since it was configured"):
        parse_latency(dist.text)
    path.write_text("0.1\nfast\n")
    with pytest.raises(LatencyError, match="line 2"):
        parse_latency(f"trace:{path}")


def test_one_inference_in_flight_chunks_never_arrive_out_of_order():
    """With a wide distribution a later request could be faster, but the core starts request k + 1 only
    after chunk k took effect: due ticks strictly increase and chunks apply in request order."""
    dist = parse_latency("lognormal:0.2:0.9")
    for merge, threshold in (("replace", None), ("weighted_average", None), ("temporal_ensemble", None)):
        core = ExecutorCore(
            ExecutorConfig(mode="async", latency=dist, latency_stream=(3,), merge=merge, request_threshold=threshold)
        )
        requests, applied, pending = [], [], {}
        for t in range(300):
            while True:
                step = core.advance(t)
                if isinstance(step, ObservationNeeded):
                    assert not pending, "a request while another is in flight"
                    requests.append(step.request)
                    pending[step.request.request_id] = np.zeros((10, 7))
                elif isinstance(step, ChunkDue):
                    core.deliver(step.request.request_id, pending.pop(step.request.request_id))
                    applied.append((t, step.request.request_id))
                else:
                    break
        assert [rid for _, rid in applied] == sorted(rid for _, rid in applied)
        assert all(b.tick >= a.due_tick for a, b in zip(requests, requests[1:], strict=False))
        assert all(r.latency_ticks == dist.ticks((3,), r.request_id) for r in requests)
        assert len({r.latency_ticks for r in requests}) > 3  # the draws did vary
        with pytest.raises(RuntimeError, match="outstanding"):
            core.deliver(999, np.zeros((10, 7)))


def test_sync_hold_lasts_each_draw():
    dist = parse_latency("uniform:0.0:0.3")
    core = ExecutorCore(ExecutorConfig(mode="sync", latency=dist, latency_stream=(11,), replan_steps=2))
    holds, req = [], None
    for t in range(60):
        while True:
            step = core.advance(t)
            if isinstance(step, ObservationNeeded):
                req = step.request
            elif isinstance(step, ChunkDue):
                core.deliver(step.request.request_id, np.zeros((4, 7)))
            else:
                holds.append((t, step.source.value, req.request_id))
                break
    for rid in {r for _, _, r in holds}:
        held = sum(1 for _, s, r in holds if r == rid and s != 0)
        n = dist.ticks((11,), rid)
        assert held == n or rid == max(r for _, _, r in holds)  # the last one may be cut by the end


def test_every_episode_of_a_cell_draws_its_own_latencies():
    """A sweep cell (one seed, several tasks and init states) samples the distribution once per episode,
    not one realisation shared by all: request k's draw depends on the suite, task and init state too."""
    dist = parse_latency("uniform:0.05:0.35")
    cell = [
        RunConfig(suite="libero_spatial", task=t, init=i, latency_dist=dist.text) for t in range(5) for i in range(2)
    ]
    first = [request_latency(c.latency_dist, c.latency_stream(), 1)[0] for c in cell]
    assert len(set(first)) > 1  # a shared draw would make all ten equal
    streams = {c.latency_stream() for c in cell}
    assert len(streams) == len(cell)
    other_suite = RunConfig(suite="libero_object", task=0, init=0, latency_dist=dist.text).latency_stream()
    assert other_suite not in streams
    # The draws are a pure function of the episode: the executor core of each episode applies the same N.
    for cfg in cell[:3]:
        core = ExecutorCore(cfg.executor_config())
        step = core.advance(0)
        assert isinstance(step, ObservationNeeded)
        assert step.request.latency_ticks == request_latency(cfg.latency_dist, cfg.latency_stream(), 1)[0]
    # Pooled over a cell of 100 episodes the first draws follow the distribution (N = 1..7, mean 4 ticks).
    many = [RunConfig(task=t, init=i, latency_dist=dist.text) for t in range(10) for i in range(10)]
    n1 = np.array([request_latency(c.latency_dist, c.latency_stream(), 1)[0] for c in many])
    assert set(n1) <= set(range(1, 8)) and abs(n1.mean() - dist.mean_ticks()) < 0.5


def test_empirical_resamples_the_measured_delays(tmp_path):
    """empirical:FILE draws each request's delay i.i.d. from the file's values (a fitted delay distribution)."""
    path = tmp_path / "fitted.txt"
    path.write_text("# request-to-effect delays, s\n0.1\n0.1\n0.15\n0.2\n")  # 2, 2, 3, 4 ticks
    dist = parse_latency(f"empirical:{path}")
    assert dist.kind == "empirical" and dist.label == "empirical:fitted.txt" and parse_latency(dist.text) == dist
    assert dist.mean_ticks() == 2.75 and (dist.min_ticks(), dist.max_ticks()) == (2, 4)
    streams = [latency_stream(7, "libero_spatial", t, i) for t in range(10) for i in range(20)]
    ticks = np.array([dist.ticks(s, k) for s in streams for k in range(1, 11)])
    assert set(ticks) == {2, 3, 4}
    assert abs((ticks == 2).mean() - 0.5) < 0.05 and abs((ticks == 4).mean() - 0.25) < 0.05
    assert abs(ticks.mean() - dist.mean_ticks()) < 0.05
    # Not a replay: consecutive requests of one episode are not the file's order.
    assert [dist.ticks(streams[0], k) for k in range(1, 21)] != [[2, 2, 3, 4][(k - 1) % 4] for k in range(1, 21)]
    assert label_of(dist.text) == "empirical:fitted.txt"


# -- bounds, checked once; a file read once ---------------------------------------------------------------------
@pytest.mark.parametrize(
    "text, fragment",
    [
        ("1e308", "the constant latency 1e+308 is outside 0..10 s"),  # OverflowError traceback
        ("1e300", "the constant latency 1e+300 is outside 0..10 s"),  # accepted, then "File name too long"
        ("10.05", "outside 0..10 s"),
        ("inf", "must be finite"),
        ("uniform:0:1e308", "a parameter 1e+308 is outside 0..10 s"),
        ("normal:1e300:1", "a parameter 1e+300 is outside"),
        ("lognormal:9:9", "applied mean"),
    ],
)
def test_latencies_are_bounded_in_one_place(text, fragment):
    with pytest.raises(LatencyError, match=re.escape(fragment)) as refused:
        parse_latency(text)
    assert "\n" not in str(refused.value)
    with pytest.raises(ValueError, match="outside 0..10 s|must be finite|applied mean"):
        RunConfig(latency_s=float(text)) if ":" not in text else RunConfig(latency_dist=text)
    assert parse_latency(MAX_LATENCY_S).params == (MAX_LATENCY_S,)


@pytest.mark.parametrize("kind", ["trace", "empirical"])
def test_a_file_value_beyond_the_bound_is_one_line(tmp_path, kind):
    """An empirical file holding 1e308: its mean overflowed (OverflowError traceback)."""
    path = tmp_path / "delays.txt"
    path.write_text("0.1\n1e308\n")
    with pytest.raises(LatencyError, match=r"line 2: '1e308' is not a latency in 0..10 s"):
        parse_latency(f"{kind}:{path}")


def test_a_trace_file_is_read_once(tmp_path, monkeypatch):
    """Its hash is of the bytes its values came from: a second read (swapped to /dev/zero between) never happens."""
    import hashlib
    from pathlib import Path as P

    path = tmp_path / "delays.txt"
    path.write_bytes(b"0.1\n0.25\n")

    def second_read(self, *args, **kwargs):
        raise AssertionError(f"{self} read a second time")

    monkeypatch.setattr(P, "read_bytes", second_read)
    monkeypatch.setattr(P, "read_text", second_read)
    dist = parse_latency(f"trace:{path}")
    assert dist.trace == (0.1, 0.25) and dist.trace_sha == hashlib.sha256(b"0.1\n0.25\n").hexdigest()[:16]
