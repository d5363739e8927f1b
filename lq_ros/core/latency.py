"""Injected latency as a distribution: one Δt_sim draw per inference, rounded up to whole control ticks.

Syntax (``--latency``, sweep ``latencies_s`` entries, ``RunConfig.latency_dist``):

Every latency, distribution parameter and file value lies in 0..:data:`MAX_LATENCY_S` seconds, and so does a
distribution's applied mean: checked here, once, for the command line, sweep specs and stored runs alike.

- ``0.2``: a constant (seconds; whole ticks, as before: see :func:`lq_ros.core.suite_constants.latency_ticks`);
- ``uniform:LO:HI``: uniform on [LO, HI] s;
- ``normal:MEAN:STD``: normal truncated at 0 (the draw is conditioned on Δt >= 0, not clipped);
- ``lognormal:MEDIAN:SIGMA``: exp(ln MEDIAN + SIGMA z), z standard normal;
- ``empirical:FILE``: the same file format, drawn i.i.d. (each request picks a line uniformly at random): the
  empirical distribution of measured delays, e.g. fitted on some real-time episodes and used on others;
- ``trace:FILE``: seconds, one per line (blank lines and ``#`` comments ignored), e.g. the Δt_real series of a
  real policy server; request k (1, 2, ...) gets line ``(offset + k - 1) mod len``, the episode's seeded offset
  (below): replayed in order and wrapped. The
  canonical text carries the content hash (``trace:FILE@sha256:0123abcd...``) so a changed file is a
  different configuration (and a stale hash is refused).

**One draw per inference, reproducible, independent across episodes.** Request k of an episode draws
u ~ U[0, 1) from its own generator: PCG64 seeded with the sequence (seed, suite, task, init, k, a fixed
tag), the episode's *latency stream* (:func:`latency_stream`) followed by k. The draw does not depend on how
many draws came before, on the transport, or on wall-clock time, so lockstep episodes stay bit-reproducible;
and because the stream names the episode, the episodes of a sweep cell (same seed, other tasks and init
states) get independent draws: a 10-episode ``uniform`` cell samples the distribution ten times over, not
one realisation ten times. A trace starts at a seeded offset per episode (drawn from the same stream with
k = 0) and is replayed in order from there, wrapped. The sample is the distribution's inverse CDF at u
(pure-Python, ``statistics.NormalDist``).

**Rounding: up to the next tick boundary.** An inference taking Δt s delivers its chunk Δt after the
observation; the simulator advances in whole ticks of dt_c = 0.05 s, so the chunk can take effect at the
first tick boundary at or after that instant: N = ceil(Δt / dt_c) (a draw within 1e-9 ticks of a boundary
counts as on it). The applied Δt_sim = N dt_c is what the bag records (ActionChunk.injected_latency_s,
the chunk's log time is observation time + N dt_c). A chunk is never applied before it exists; the price
is that the applied mean exceeds the raw mean by up to one tick (``uniform:0.1:0.3`` applies 0.225 s on
average, ``uniform:0.075:0.275`` exactly 0.2 s). :meth:`LatencyDist.mean_ticks` is that applied mean,
computed exactly (a sum over ticks of the survival function), and is what rows and plots are labelled by.

The executor core and the ROS policy node both call :func:`request_latency` with the run's distribution,
latency stream and request id: one function, one answer.
"""

from __future__ import annotations

import hashlib
import math
import zlib
from collections.abc import Sequence
from dataclasses import dataclass
from functools import cache
from pathlib import Path
from statistics import NormalDist

import numpy as np

from lq_ros.core.bounded_file import FileRefused, read_regular_file
from lq_ros.core.suite_constants import CONTROL_DT_S, latency_ticks

KINDS = ("constant", "uniform", "normal", "lognormal", "trace", "empirical")
#: Kinds whose values come from a file (trace: replayed in order; empirical: resampled).
FILE_KINDS = ("trace", "empirical")
#: Mixed into every draw's seed sequence so latency draws never coincide with other seeded streams.
_TAG = 0x4C51_4C41  # "LQLA"
#: A draw this close (in ticks) above a tick boundary is on the boundary (floating point of e.g. 0.15 / 0.05).
_TICK_TOL = 1e-9
_STD_NORMAL = NormalDist()
#: The words that name an episode's latency draws: (seed, suite, task, init) as unsigned 32-bit integers
#: (:func:`latency_stream`). A bare integer is read as the one-word stream (seed,).
Stream = Sequence[int] | int


class LatencyError(ValueError):
    """A latency specification that cannot be used; the message says what is wrong."""


def ticks_of_draw(delay_s: float, control_dt_s: float = CONTROL_DT_S) -> int:
    """N = ceil(Δt / dt_c): the first tick boundary at or after the draw (see the module docstring)."""
    if not delay_s >= 0 or not math.isfinite(delay_s):
        raise LatencyError(f"a latency draw must be finite and >= 0 s, got {delay_s}")
    return max(0, math.ceil(delay_s / control_dt_s - _TICK_TOL))


def applied_seconds(ticks: int, control_dt_s: float = CONTROL_DT_S) -> float:
    """Δt_sim = N dt_c, rounded to 1 ns (so 3 ticks is 0.15, not 0.15000000000000002)."""
    return round(ticks * control_dt_s, 9)


def _number(text: str, what: str, spec: str) -> float:
    try:
        value = float(text if text.isascii() else "not ASCII")  # float() takes any script's digits: only 0-9 here
    except ValueError:
        raise LatencyError(f"latency {spec!r}: {what} {text!r} is not a number (digits 0-9)") from None
    if not math.isfinite(value):
        raise LatencyError(f"latency {spec!r}: {what} must be finite, got {text}")
    return value


#: The largest trace file read (bytes): a trace is a text file of seconds, one per line.
MAX_TRACE_BYTES = 1 << 20
#: The largest latency, s: a constant, a distribution's parameter, a file's value, an applied mean (an episode's
#: whole budget is at most 26 s; 1e300 s made episode names too long for the file system).
MAX_LATENCY_S = 10.0


def _bounded(value: float, what: str, spec: str) -> float:
    if not 0 <= value <= MAX_LATENCY_S:
        raise LatencyError(f"latency {spec!r}: {what} {value:g} is outside 0..{MAX_LATENCY_S:g} s")
    return value


def _read_trace(path: Path, spec: str) -> tuple[tuple[float, ...], str]:
    """The values of a trace file and the sha256 of the bytes they were read from: a regular text file of at most
    MAX_TRACE_BYTES (never a device or pipe), read once (a file swapped between two reads cannot differ)."""
    try:
        data = read_regular_file(path, MAX_TRACE_BYTES, "trace")
    except FileRefused as exc:
        raise LatencyError(f"latency {spec!r}: {exc} (a trace is a text file of seconds)") from None
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError:
        text = "\0"
    if "\0" in text:
        raise LatencyError(f"latency trace {path}: not a text file (a trace is seconds as text, one number per line)")
    lines = text.splitlines()
    values = []
    for i, line in enumerate(lines, 1):
        text = line.split("#", 1)[0].strip()
        if not text:
            continue
        try:
            value = float(text if text.isascii() else "not ASCII")  # digits 0-9 only
        except ValueError:
            raise LatencyError(f"latency trace {path}, line {i}: {text!r} is not a number of seconds") from None
        if not (math.isfinite(value) and 0 <= value <= MAX_LATENCY_S):
            raise LatencyError(f"latency trace {path}, line {i}: {text!r} is not a latency in 0..{MAX_LATENCY_S:g} s")
        values.append(value)
    if not values:
        raise LatencyError(f"latency trace {path}: no values (seconds, one per line)")
    return tuple(values), hashlib.sha256(data).hexdigest()[:16]


@dataclass(frozen=True)
class LatencyDist:
    """A parsed latency distribution; build it with :func:`parse_latency`."""

    kind: str
    params: tuple[float, ...] = ()
    #: trace: the values (s) in file order; its path and content hash.
    trace: tuple[float, ...] = ()
    trace_path: str = ""
    trace_sha: str = ""

    @property
    def text(self) -> str:
        """Canonical text: parses back to this distribution (RunConfig stores it)."""
        if self.kind == "constant":
            return f"{self.params[0]:g}"
        if self.kind in FILE_KINDS:
            return f"{self.kind}:{self.trace_path}@sha256:{self.trace_sha}"
        return ":".join([self.kind, *(f"{p:g}" for p in self.params)])

    @property
    def label(self) -> str:
        """Short label for rows and plots: e.g. ``uniform:0.075:0.275``, ``trace:server.txt``, ``constant``."""
        if self.kind == "constant":
            return "constant"
        if self.kind in FILE_KINDS:
            return f"{self.kind}:{Path(self.trace_path).name}"
        return self.text

    def draw_s(self, stream: Stream, request_id: int) -> float:
        """The raw Δt (s) of request ``request_id`` (1, 2, ...) in the episode of latency stream ``stream``."""
        if self.kind == "constant":
            return self.params[0]
        if self.kind == "trace":
            return self.trace[(self.trace_offset(stream) + request_id - 1) % len(self.trace)]
        u = _uniform(stream, request_id)
        if self.kind == "empirical":
            return self.trace[min(int(u * len(self.trace)), len(self.trace) - 1)]
        if self.kind == "uniform":
            lo, hi = self.params
            return lo + (hi - lo) * u
        if self.kind == "normal":
            mean, std = self.params
            below = _STD_NORMAL.cdf(-mean / std)  # P(X < 0), cut off by the truncation
            p = min(max(below + u * (1.0 - below), 1e-300), 1.0 - 2.0**-53)
            return max(0.0, mean + std * _STD_NORMAL.inv_cdf(p))
        median, sigma = self.params
        return median * math.exp(sigma * _STD_NORMAL.inv_cdf(min(max(u, 2.0**-60), 1.0 - 2.0**-53)))

    def trace_offset(self, stream: Stream) -> int:
        """trace: the line (0-based) request 1 of the episode of ``stream`` replays; 0 for other kinds."""
        if self.kind != "trace":
            return 0
        return min(int(_uniform(stream, 0) * len(self.trace)), len(self.trace) - 1)

    def ticks(self, stream: Stream, request_id: int) -> int:
        """Applied N of request ``request_id``: the draw rounded up to whole ticks (constant: exact)."""
        if self.kind == "constant":
            return latency_ticks(self.params[0])
        return ticks_of_draw(self.draw_s(stream, request_id))

    def survival(self, x_s: float) -> float:
        """P(Δt > x) of the raw draw (continuous kinds)."""
        if self.kind == "uniform":
            lo, hi = self.params
            if hi == lo:
                return 1.0 if x_s < lo else 0.0
            return min(1.0, max(0.0, (hi - x_s) / (hi - lo)))
        if self.kind == "normal":
            mean, std = self.params
            keep = 1.0 - _STD_NORMAL.cdf(-mean / std)
            return 1.0 if x_s < 0 else (1.0 - _STD_NORMAL.cdf((x_s - mean) / std)) / keep
        if self.kind == "lognormal":
            median, sigma = self.params
            return 1.0 if x_s <= 0 else 1.0 - _STD_NORMAL.cdf(math.log(x_s / median) / sigma)
        raise LatencyError(f"no survival function for a {self.kind} latency")

    def mean_ticks(self) -> float:
        """Expected applied N (exact): constant N, the trace's mean N, else sum_k P(N > k) = sum_k S(k dt_c)."""
        return round(_mean_ticks(self), 6)

    def mean_s(self) -> float:
        """Expected applied Δt_sim = E[N] dt_c, rounded to 1 ns: the value rows and plots are labelled by."""
        return round(self.mean_ticks() * CONTROL_DT_S, 9)

    def nominal_ticks(self) -> int:
        """The expected N rounded up: what the strategies' default request thresholds use."""
        return max(0, math.ceil(self.mean_ticks() - 1e-9))

    def min_ticks(self) -> int:
        """The smallest N a draw can apply (an explicit request threshold at or below it never overlaps)."""
        if self.kind == "constant":
            return latency_ticks(self.params[0])
        if self.kind in FILE_KINDS:
            return min(ticks_of_draw(v) for v in self.trace)
        if self.kind == "uniform":
            return ticks_of_draw(self.params[0])
        return 0  # normal truncated at 0, lognormal: arbitrarily close to 0

    def max_ticks(self) -> int | None:
        """The largest N a draw can apply (None: unbounded)."""
        if self.kind == "constant":
            return latency_ticks(self.params[0])
        if self.kind in FILE_KINDS:
            return max(ticks_of_draw(v) for v in self.trace)
        if self.kind == "uniform":
            return ticks_of_draw(self.params[1])
        return None


@cache
def _mean_ticks(dist: LatencyDist) -> float:
    if dist.kind == "constant":
        return float(latency_ticks(dist.params[0]))
    if dist.kind in FILE_KINDS:
        return float(np.mean([ticks_of_draw(v) for v in dist.trace]))
    # P(N > k) = P(Δt > (k + tol) dt_c), the rounding of ticks_of_draw.
    total, k = 0.0, 0
    while True:
        a = (k + _TICK_TOL) * CONTROL_DT_S
        s = dist.survival(a)
        if s < 1e-15:
            return total
        if k >= 100_000:
            # A heavy lognormal tail: the rest in closed form, sum_k S(k dt) ~ E[(Δt - a)+] / dt + S(a) / 2.
            median, sigma = dist.params
            z = math.log(median / a) / sigma
            excess = median * math.exp(sigma**2 / 2) * _STD_NORMAL.cdf(z + sigma) - a * _STD_NORMAL.cdf(z)
            return total + excess / CONTROL_DT_S + s / 2
        total += s
        k += 1


def latency_stream(seed: int, suite: str, task: int, init: int) -> tuple[int, ...]:
    """The latency stream of one episode: its draws differ from every other episode's of the same sweep.

    The suite enters as its CRC-32 (stable across Python processes, unlike ``hash``).
    """
    return (int(seed) & 0xFFFFFFFF, zlib.crc32(suite.encode()), int(task) & 0xFFFFFFFF, int(init) & 0xFFFFFFFF)


def _uniform(stream: Stream, request_id: int) -> float:
    """u ~ U[0, 1) of one request: its own PCG64 stream seeded by (latency stream..., request id, tag)."""
    words = [int(stream) & 0xFFFFFFFF] if isinstance(stream, int) else [int(w) & 0xFFFFFFFF for w in stream]
    gen = np.random.Generator(np.random.PCG64(np.random.SeedSequence([*words, int(request_id), _TAG])))
    return float(gen.random())


def parse_latency(spec: str | float | int) -> LatencyDist:
    """Parse a latency specification (see the module docstring); LatencyError says what is wrong."""
    if isinstance(spec, bool):
        raise LatencyError(f"latency: expected seconds or a distribution, got {spec!r}")
    if isinstance(spec, int | float):
        spec = repr(float(spec))
    text = str(spec).strip()
    kind, _, rest = text.partition(":")
    if not rest:
        value = _bounded(_number(text, "the constant latency", text), "the constant latency", text)
        try:
            latency_ticks(value)
        except ValueError as exc:
            raise LatencyError(str(exc)) from None
        return LatencyDist("constant", (value,))
    if kind in FILE_KINDS:
        path_text, _, sha = rest.partition("@sha256:")
        path = Path(path_text).expanduser()
        values, digest = _read_trace(path, text)
        if sha and sha != digest:
            raise LatencyError(
                f"latency {text!r}: {path} changed since it was configured (content sha256 {digest}..., "
                f"configured {sha}...)"
            )
        return LatencyDist(kind, (), values, str(path), digest)
    if kind not in KINDS:
        raise LatencyError(
            f"latency {text!r}: unknown distribution {kind!r}; use seconds or one of uniform:LO:HI, "
            "normal:MEAN:STD, lognormal:MEDIAN:SIGMA, trace:FILE, empirical:FILE"
        )
    parts = rest.split(":")
    if len(parts) != 2:
        names = {"uniform": "LO:HI", "normal": "MEAN:STD", "lognormal": "MEDIAN:SIGMA"}[kind]
        raise LatencyError(f"latency {text!r}: expected {kind}:{names}")
    a, b = (_number(p, "parameter", text) for p in parts)
    if kind == "uniform" and not 0 <= a <= b:
        raise LatencyError(f"latency {text!r}: expected 0 <= LO <= HI")
    if kind == "normal" and not (a >= 0 and b > 0):
        raise LatencyError(f"latency {text!r}: expected MEAN >= 0 and STD > 0")
    if kind == "lognormal" and not (a > 0 and b > 0):
        raise LatencyError(f"latency {text!r}: expected MEDIAN > 0 and SIGMA > 0")
    for value in (a, b):
        _bounded(value, "a parameter", text)
    dist = LatencyDist(kind, (a, b))
    if dist.mean_s() > MAX_LATENCY_S:
        raise LatencyError(f"latency {text!r}: applied mean {dist.mean_s():.4g} s is over {MAX_LATENCY_S:g} s")
    return dist


def label_of(text: str | None) -> str:
    """The label of a stored distribution text without reading a trace file (the scorer's): ``constant``
    for an empty text or seconds."""
    text = (text or "").strip()
    if not text or ":" not in text:
        return "constant"
    kind, _, rest = text.partition(":")
    if kind in FILE_KINDS:
        return f"{kind}:" + Path(rest.partition("@sha256:")[0]).name
    return text


@cache
def _parsed(text: str) -> LatencyDist:
    return parse_latency(text)


def request_latency(dist: LatencyDist | str, stream: Stream, request_id: int) -> tuple[int, float]:
    """(N, applied Δt_sim s) of request ``request_id`` in the episode of latency stream ``stream``
    (:func:`latency_stream`): the one function both the executor core and the ROS policy node call."""
    d = _parsed(dist) if isinstance(dist, str) else dist
    n = d.ticks(stream, request_id)
    return n, (d.params[0] if d.kind == "constant" else applied_seconds(n))
