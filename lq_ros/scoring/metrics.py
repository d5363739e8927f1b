"""Trajectory-quality, energy and time-to-success metrics for LIBERO-LQ (pure numpy/scipy, no ROS, no I/O).

Definitions follow the LIBERO-LQ paper, appendix A (jerk, EE-Osc, trajectory length) and appendix B
(energy model), plus two standard smoothness measures on the speed profile (SPARC and log dimensionless
jerk, Balasubramanian et al. 2015; Hogan & Sternad 2009).

Units: positions in metres, times in seconds, frequencies in hertz, torques in N m, joint velocities in
rad/s, energies in joules. Every finite-difference metric depends on the sampling interval: always report
the sampling rate next to the number (jerk amplifies high-frequency noise by ``1 / dt**3``).

All sampled-signal functions assume *uniform* sampling; use :func:`check_uniform` to detect gaps and
:func:`resample_uniform` to fix them before scoring.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = [
    "DEFAULT_OSC_WINDOW",
    "ELEC_LOSS_COEFF_W_PER_NM2",
    "OVERHEAD_POWER_W",
    "SPARC_AMP_THRESHOLD",
    "SPARC_FC_HZ",
    "MIN_MOVEMENT_SPEED_M_S",
    "SPARC_PADLEVEL",
    "EnergyTerms",
    "check_uniform",
    "dimensionless_jerk",
    "ee_oscillation",
    "ee_oscillation_detrended",
    "energy_from_integrals",
    "restricted_mean_time",
    "energy_terms",
    "jerk_mean",
    "jerk_norms",
    "jerk_p90",
    "ldlj",
    "resample_uniform",
    "sparc",
    "speed_profile",
    "trajectory_length",
]

#: Electrical loss coefficient R * Kt^-2 of the simplified DC-motor model, W / (N m)^2 (paper eq. 8,
#: value from Petrichenko et al. 2024).
ELEC_LOSS_COEFF_W_PER_NM2 = 0.0036
#: Constant controller/electronics overhead power, W (measured Franka Emika idle power, paper B.1).
OVERHEAD_POWER_W = 85.0
#: EE-Osc window K, in samples of the position series passed in. The paper only says "a short temporal
#: window of the last K steps" without a value; we use K = 10 control steps = 0.5 s at the 20 Hz LIBERO
#: control rate, which is one pi05_libero action chunk (10 actions) and two replan cycles
#: (replan_steps=5), so the window always spans at least one policy update. Pass control-rate (20 Hz)
#: positions for this default to mean 0.5 s.
DEFAULT_OSC_WINDOW = 10

#: SPARC defaults (Balasubramanian et al. 2015): zero-padding level, maximum cut-off (Hz), amplitude
#: threshold of the normalised spectrum for the adaptive cut-off.
SPARC_PADLEVEL = 4
SPARC_FC_HZ = 10.0
SPARC_AMP_THRESHOLD = 0.05
#: Below this peak speed (m/s) a trajectory counts as motionless: SPARC and LDLJ describe the shape of a
#: movement and are undefined without one (on simulator noise they would report "perfectly smooth").
MIN_MOVEMENT_SPEED_M_S = 1e-3


# --------------------------------------------------------------------------------------------------
# validation helpers
# --------------------------------------------------------------------------------------------------


def _check_dt(dt_s: float) -> float:
    dt = float(dt_s)
    if not math.isfinite(dt) or dt <= 0.0:
        raise ValueError(f"sampling interval dt_s must be a positive finite number of seconds, got {dt_s!r}")
    return dt


def _as_positions(pos: ArrayLike) -> NDArray[np.float64]:
    p = np.asarray(pos, dtype=np.float64)
    if p.ndim == 1:
        p = p[:, None]
    if p.ndim != 2:
        raise ValueError(f"positions must have shape (T, D) (e.g. (T, 3) metres), got shape {p.shape}")
    return p


def _as_speed(speed: ArrayLike) -> NDArray[np.float64]:
    v = np.asarray(speed, dtype=np.float64)
    if v.ndim != 1:
        raise ValueError(f"speed profile must be 1-D (T,), got shape {v.shape}")
    if v.size == 0:
        raise ValueError("speed profile is empty")
    if not np.all(np.isfinite(v)):
        raise ValueError("speed profile contains non-finite values")
    return v


# --------------------------------------------------------------------------------------------------
# jerk, oscillation, path length (appendix A)
# --------------------------------------------------------------------------------------------------


def jerk_norms(pos: ArrayLike, dt_s: float) -> NDArray[np.float64]:
    """Norms of the finite-difference jerk of an end-effector path (paper eq. 4).

    ``j_t = (p_t - 3 p_{t-1} + 3 p_{t-2} - p_{t-3}) / dt**3`` for t = 4..T (1-based).

    Args:
        pos: (T, 3) end-effector positions in metres, uniformly sampled.
        dt_s: sampling interval in seconds.

    Returns:
        (T-3,) jerk norms in m/s^3.

    Raises:
        ValueError: if T < 4 (jerk needs four samples) or dt_s is not positive.
    """
    p = _as_positions(pos)
    dt = _check_dt(dt_s)
    if p.shape[0] < 4:
        raise ValueError(f"jerk needs at least 4 position samples, got T={p.shape[0]}")
    j = (p[3:] - 3.0 * p[2:-1] + 3.0 * p[1:-2] - p[:-3]) / dt**3
    return np.linalg.norm(j, axis=1)


def jerk_mean(pos: ArrayLike, dt_s: float) -> float:
    """Mean jerk norm over t = 4..T (paper eq. 5), m/s^3. Raises ValueError if T < 4."""
    return float(np.mean(jerk_norms(pos, dt_s)))


def jerk_p90(pos: ArrayLike, dt_s: float) -> float:
    """90th percentile (numpy linear interpolation) of the jerk norms, m/s^3. Raises ValueError if T < 4."""
    return float(np.percentile(jerk_norms(pos, dt_s), 90.0))


def _osc_tail(pos: ArrayLike, window: int) -> NDArray[np.float64]:
    """The last ``window`` positions (all of them if fewer); ValueError for an empty series or window < 1."""
    p = _as_positions(pos)
    if window < 1:
        raise ValueError(f"EE-Osc window must be >= 1 sample, got {window}")
    if p.shape[0] == 0:
        raise ValueError("EE-Osc needs at least one position sample, got none")
    return p[-window:]


def ee_oscillation(pos: ArrayLike, window: int = DEFAULT_OSC_WINDOW) -> float:
    """End-effector oscillation EE-Osc (paper A.3), metres.

    Mean Euclidean distance of the last ``window`` positions from their own mean. If fewer than
    ``window`` samples are available, all samples are used.

    Args:
        pos: (T, 3) end-effector positions in metres.
        window: K, number of trailing samples (see :data:`DEFAULT_OSC_WINDOW`).

    Raises:
        ValueError: if ``pos`` is empty or ``window`` < 1.
    """
    tail = _osc_tail(pos, window)
    return float(np.mean(np.linalg.norm(tail - tail.mean(axis=0), axis=1)))


def ee_oscillation_detrended(pos: ArrayLike, window: int = DEFAULT_OSC_WINDOW) -> float:
    """EE-Osc about the least-squares straight line through the last ``window`` positions, metres.

    The paper's EE-Osc (:func:`ee_oscillation`) measures the spread of the last K samples about their
    mean, so on an arm still travelling at the end it mostly measures travel (K samples of a 0.1 m/s
    motion spread by ~2 cm). Here each axis is fitted by ``a + b k`` over the window (k = sample
    index) and the mean Euclidean distance from that line is returned: only back-and-forth remains.
    Fewer than ``window`` samples: all are used; with one or two samples the result is 0.

    Raises:
        ValueError: if ``pos`` is empty or ``window`` < 1.
    """
    tail = _osc_tail(pos, window)
    k = np.arange(len(tail), dtype=np.float64)
    design = np.column_stack([np.ones_like(k), k])
    coef, *_ = np.linalg.lstsq(design, tail, rcond=None)
    return float(np.mean(np.linalg.norm(tail - design @ coef, axis=1)))


def trajectory_length(pos: ArrayLike) -> float:
    """Path length ``sum_t ||p_t - p_{t-1}||`` in metres (paper A.4); 0 for fewer than two samples."""
    p = _as_positions(pos)
    if p.shape[0] < 2:
        return 0.0
    return float(np.sum(np.linalg.norm(np.diff(p, axis=0), axis=1)))


def speed_profile(pos: ArrayLike, dt_s: float) -> NDArray[np.float64]:
    """Speed ``||p_t - p_{t-1}|| / dt`` in m/s, shape (T-1,), from (T, 3) positions in metres."""
    p = _as_positions(pos)
    dt = _check_dt(dt_s)
    if p.shape[0] < 2:
        raise ValueError(f"speed profile needs at least 2 position samples, got T={p.shape[0]}")
    return np.linalg.norm(np.diff(p, axis=0), axis=1) / dt


# --------------------------------------------------------------------------------------------------
# energy (appendix B)
# --------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class EnergyTerms:
    """Trajectory-level energy split into the terms of paper eq. (9), all in joules.

    Attributes:
        mech_j: positive mechanical work ``sum max(0, tau . qdot) dt`` (eq. 6-7).
        elec_j: resistive loss ``sum coeff * tau . tau dt`` (eq. 8).
        overhead_j: constant overhead ``T * P_overhead * dt``.
        total_j: E_traj = mech + elec + overhead (eq. 9).
        per_step_j: E_norm = E_traj / T, joules per sample (eq. 10).
        n_steps: T, number of samples integrated.
    """

    mech_j: float
    elec_j: float
    overhead_j: float
    total_j: float
    per_step_j: float
    n_steps: int


def energy_terms(
    torque: ArrayLike,
    joint_vel: ArrayLike,
    dt_s: float,
    elec_coeff: float = ELEC_LOSS_COEFF_W_PER_NM2,
    overhead_w: float = OVERHEAD_POWER_W,
) -> EnergyTerms:
    """Trajectory energy from joint torques and velocities (paper eq. 6-10), rectangle-rule integration.

    Args:
        torque: (T, J) joint torques in N m (e.g. ``sensor_msgs/JointState.effort``).
        joint_vel: (T, J) joint velocities in rad/s, same shape as ``torque``.
        dt_s: uniform sampling interval in seconds (each sample contributes ``power * dt_s``).
        elec_coeff: R * Kt^-2 in W / (N m)^2.
        overhead_w: constant overhead power in W.

    Raises:
        ValueError: on shape mismatch, T == 0, non-finite input, or non-positive dt_s.
    """
    tau = np.asarray(torque, dtype=np.float64)
    qd = np.asarray(joint_vel, dtype=np.float64)
    dt = _check_dt(dt_s)
    if tau.ndim == 1:
        tau = tau[:, None]
    if qd.ndim == 1:
        qd = qd[:, None]
    if tau.ndim != 2 or tau.shape != qd.shape:
        raise ValueError(f"torque and joint_vel must both be (T, J) with equal shapes, got {tau.shape} and {qd.shape}")
    n = tau.shape[0]
    if n == 0:
        raise ValueError("energy needs at least one sample, got T=0")
    if not (np.all(np.isfinite(tau)) and np.all(np.isfinite(qd))):
        raise ValueError("torque / joint_vel contain non-finite values")
    p_mech = np.maximum(0.0, np.einsum("tj,tj->t", tau, qd))
    p_elec = float(elec_coeff) * np.einsum("tj,tj->t", tau, tau)
    mech = float(np.sum(p_mech) * dt)
    elec = float(np.sum(p_elec) * dt)
    overhead = float(n * float(overhead_w) * dt)
    total = mech + elec + overhead
    return EnergyTerms(mech_j=mech, elec_j=elec, overhead_j=overhead, total_j=total, per_step_j=total / n, n_steps=n)


def energy_from_integrals(
    positive_work_j: ArrayLike,
    torque_squared_integral: ArrayLike,
    duration_s: ArrayLike,
    steps: int,
    elec_coeff: float = ELEC_LOSS_COEFF_W_PER_NM2,
    overhead_w: float = OVERHEAD_POWER_W,
) -> EnergyTerms:
    """Trajectory energy (eq. 6-10) from per-interval integrals computed at the physics rate.

    Each interval (one control tick) carries ``sum max(0, tau . qdot) dt`` (J), ``sum tau . tau dt``
    (N^2 m^2 s) and its length (s), all summed over its physics substeps; the trajectory's terms are
    their sums (eq. 8's coefficient and eq. 9's overhead power applied here).

    Args:
        positive_work_j, torque_squared_integral, duration_s: (T,) one entry per interval.
        steps: T in eq. 10, the number of control steps the energy is normalised by.

    Raises:
        ValueError: no interval, non-finite values, negative integrals or steps < 1.
    """
    work = np.asarray(positive_work_j, dtype=np.float64).reshape(-1)
    torque_sq = np.asarray(torque_squared_integral, dtype=np.float64).reshape(-1)
    duration = np.asarray(duration_s, dtype=np.float64).reshape(-1)
    if not work.size or not (work.size == torque_sq.size == duration.size):
        raise ValueError(
            f"need one value of each integral per interval, got {work.size}, {torque_sq.size}, {duration.size}"
        )
    if not all(np.all(np.isfinite(a)) and np.all(a >= 0.0) for a in (work, torque_sq, duration)):
        raise ValueError("energy integrals must be finite and non-negative")
    if steps < 1:
        raise ValueError(f"steps must be >= 1, got {steps}")
    mech = float(work.sum())
    elec = float(elec_coeff) * float(torque_sq.sum())
    overhead = float(overhead_w) * float(duration.sum())
    total = mech + elec + overhead
    return EnergyTerms(
        mech_j=mech, elec_j=elec, overhead_j=overhead, total_j=total, per_step_j=total / steps, n_steps=steps
    )


# --------------------------------------------------------------------------------------------------
# speed-profile smoothness: SPARC and (log) dimensionless jerk
# --------------------------------------------------------------------------------------------------


def sparc(
    speed: ArrayLike,
    fs_hz: float,
    padlevel: int = SPARC_PADLEVEL,
    fc_hz: float = SPARC_FC_HZ,
    amp_th: float = SPARC_AMP_THRESHOLD,
) -> float:
    """Spectral arc length (SPARC, Balasubramanian et al. 2015) of a speed profile; dimensionless, <= 0.

    Procedure (as in the authors' published reference implementation):
    1. zero-pad to ``nfft = 2**(ceil(log2 N) + padlevel)`` and take ``|FFT|``, normalised by its maximum;
    2. keep bins with frequency ``<= fc_hz`` (``fc_hz`` is clipped to the Nyquist frequency ``fs_hz / 2``
       so mirrored negative frequencies are never included);
    3. adaptive cut-off: keep the contiguous range from the first to the last of those bins whose
       normalised magnitude is ``>= amp_th`` (for a non-negative speed profile the first is the DC bin);
    4. return ``-sum sqrt((df / (f_c - f_0))**2 + dM**2)`` over the kept bins.

    Less negative means smoother. Reference: ``t = arange(-1, 1, 0.01)``, ``exp(-5 t**2)``, fs = 100 Hz
    gives -1.41403. Undefined (ValueError) without movement (peak speed below
    :data:`MIN_MOVEMENT_SPEED_M_S`, speed in m/s) or when fewer than two spectral bins pass the
    threshold (no arc to measure); it never reports such a case as perfectly smooth (0).

    Args:
        speed: (N,) speed profile (any unit; the spectrum is normalised).
        fs_hz: sampling frequency in Hz.
        padlevel: extra powers of two of zero padding.
        fc_hz: maximum cut-off frequency in Hz.
        amp_th: amplitude threshold of the normalised spectrum for the adaptive cut-off.

    Raises:
        ValueError: empty / non-finite / motionless profile, no spectral arc, or non-positive fs_hz.
    """
    v = _as_speed(speed)
    fs = float(fs_hz)
    if not math.isfinite(fs) or fs <= 0.0:
        raise ValueError(f"fs_hz must be a positive sampling frequency in Hz, got {fs_hz!r}")
    _require_movement(v)
    nfft = int(2 ** (math.ceil(math.log2(v.size)) + int(padlevel)))
    freqs = np.arange(nfft) * (fs / nfft)
    mag = np.abs(np.fft.fft(v, nfft))
    peak = float(mag.max())
    if peak == 0.0:
        raise ValueError("SPARC is undefined for an identically zero speed profile (no movement)")
    mag = mag / peak
    fc = min(float(fc_hz), fs / 2.0)
    in_band = freqs <= fc
    f_sel = freqs[in_band]
    m_sel = mag[in_band]
    above = np.nonzero(m_sel >= amp_th)[0]
    if above.size < 2:
        raise ValueError(f"SPARC is undefined: fewer than 2 spectral bins up to {fc:g} Hz reach {amp_th:g} of the peak")
    f_sel = f_sel[above[0] : above[-1] + 1]
    m_sel = m_sel[above[0] : above[-1] + 1]
    span = f_sel[-1] - f_sel[0]
    return float(-np.sum(np.sqrt((np.diff(f_sel) / span) ** 2 + np.diff(m_sel) ** 2)))


def _require_movement(v: NDArray[np.float64]) -> None:
    peak = float(np.max(np.abs(v)))
    if peak < MIN_MOVEMENT_SPEED_M_S:
        raise ValueError(
            f"undefined without movement: peak speed {peak:.2g} m/s < {MIN_MOVEMENT_SPEED_M_S:g} m/s "
            "(the arm did not move)"
        )


def dimensionless_jerk(speed: ArrayLike, fs_hz: float) -> float:
    """Dimensionless jerk of a speed profile (Hogan & Sternad 2009, speed-profile form); <= 0.

    ``DJ = -(T**3 / v_peak**2) * integral |d^2 v / dt^2|^2 dt`` with the discretisation that reproduces
    the published reference values (Balasubramanian et al. 2015 code):
    ``d^2v/dt^2 = np.diff(v, 2) / dt**2``, duration ``T = N * dt`` (N samples, not N-1), integral as the
    plain sum times ``dt`` (not trapezoidal), ``v_peak = max |v|``, ``dt = 1 / fs_hz``.
    Reference: ``exp(-5 t**2)``, ``t = arange(-1, 1, 0.01)``, fs = 100 Hz gives -335.74684.

    Raises:
        ValueError: fewer than 3 samples, identically zero profile, or non-positive fs_hz.
    """
    v = _as_speed(speed)
    fs = float(fs_hz)
    if not math.isfinite(fs) or fs <= 0.0:
        raise ValueError(f"fs_hz must be a positive sampling frequency in Hz, got {fs_hz!r}")
    if v.size < 3:
        raise ValueError(f"dimensionless jerk needs at least 3 speed samples, got N={v.size}")
    _require_movement(v)
    v_peak = float(np.max(np.abs(v)))
    dt = 1.0 / fs
    duration = v.size * dt
    d2v = np.diff(v, 2) / dt**2
    return float(-(duration**3 / v_peak**2) * np.sum(d2v**2) * dt)


def ldlj(speed: ArrayLike, fs_hz: float) -> float:
    """Log dimensionless jerk ``-ln |DJ|`` of a speed profile (see :func:`dimensionless_jerk`).

    Less negative means smoother. Undefined (ValueError) when DJ == 0 (a speed with zero second
    difference, e.g. constant: log of 0) and without movement. Reference: ``exp(-5 t**2)``,
    ``t = arange(-1, 1, 0.01)``, fs = 100 Hz gives -5.81636.
    """
    dj = dimensionless_jerk(speed, fs_hz)
    if dj == 0.0:
        raise ValueError("LDLJ is undefined: the speed profile has zero second difference (log of 0)")
    return -math.log(abs(dj))


# --------------------------------------------------------------------------------------------------
# sampling checks
# --------------------------------------------------------------------------------------------------


def check_uniform(t_s: ArrayLike, dt_s: float, rel_tol: float = 0.01) -> str | None:
    """Check that timestamps are uniformly spaced by ``dt_s``.

    Args:
        t_s: (T,) timestamps in seconds.
        dt_s: expected sampling interval in seconds.
        rel_tol: allowed relative deviation of each interval from ``dt_s``.

    Returns:
        ``None`` if every interval is within ``dt_s * (1 +- rel_tol)``; otherwise a human-readable reason
        for the first offending interval, e.g. ``"gap of 0.150 s at t=3.200 s (expected 0.050 s)"``
        (``t`` is the timestamp where the interval starts), prefixed with the number of bad intervals
        when there are several. Fewer than two samples are reported as a problem too.
    """
    dt = _check_dt(dt_s)
    t = np.asarray(t_s, dtype=np.float64).reshape(-1)
    if t.size < 2:
        return f"only {t.size} timestamp(s); need at least 2 to check sampling"
    if not np.all(np.isfinite(t)):
        return "timestamps contain non-finite values"
    d = np.diff(t)
    tol = dt * float(rel_tol)
    bad = np.nonzero(np.abs(d - dt) > tol)[0]
    if bad.size == 0:
        return None
    i = int(bad[0])
    if d[i] <= 0.0:
        what = f"non-increasing timestamps ({d[i]:+.3f} s)"
    elif d[i] > dt:
        what = f"gap of {d[i]:.3f} s"
    else:
        what = f"short interval of {d[i]:.3f} s"
    reason = f"{what} at t={t[i]:.3f} s (expected {dt:.3f} s)"
    if bad.size > 1:
        reason = f"{bad.size} irregular intervals; first: {reason}"
    return reason


def resample_uniform(t_s: ArrayLike, values: ArrayLike, dt_s: float) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Linearly interpolate a possibly non-uniform series onto a uniform grid.

    The grid is ``t_s[0] + k * dt_s`` for k = 0.. up to and including the last point ``<= t_s[-1]``
    (a 1e-9 relative slack absorbs float round-off), so nothing is extrapolated.

    Args:
        t_s: (T,) strictly increasing timestamps in seconds.
        values: (T,) or (T, D) samples.
        dt_s: target sampling interval in seconds.

    Returns:
        ``(t_uniform, values_uniform)`` with shapes (M,) and (M,) / (M, D).

    Raises:
        ValueError: empty input, length mismatch, or timestamps not strictly increasing.
    """
    dt = _check_dt(dt_s)
    t = np.asarray(t_s, dtype=np.float64).reshape(-1)
    y = np.asarray(values, dtype=np.float64)
    if t.size == 0:
        raise ValueError("cannot resample an empty series")
    if y.shape[0] != t.size:
        raise ValueError(f"values has {y.shape[0]} samples but t_s has {t.size}")
    if t.size > 1 and not np.all(np.diff(t) > 0.0):
        raise ValueError("timestamps must be strictly increasing")
    n = math.floor((t[-1] - t[0]) / dt + 1e-9) + 1
    t_new = t[0] + np.arange(n) * dt
    t_new[-1] = min(t_new[-1], t[-1])  # guard against round-off past the last sample
    if y.ndim == 1:
        return t_new, np.interp(t_new, t, y)
    flat = y.reshape(t.size, -1)
    out = np.column_stack([np.interp(t_new, t, flat[:, k]) for k in range(flat.shape[1])])
    return t_new, out.reshape((n,) + y.shape[1:])


# --------------------------------------------------------------------------------------------------
# time to success
# --------------------------------------------------------------------------------------------------


def restricted_mean_time(times: ArrayLike, events: ArrayLike, horizon: float) -> float:
    """Kaplan-Meier restricted mean time to success up to ``horizon`` (same unit as ``times``).

    ``times[i]`` is when episode i succeeded (``events[i]`` True) or was censored (False: a failure
    ends at its step budget, so the success time is only known to exceed it). The restricted mean
    ``integral_0^horizon S(t) dt`` of the Kaplan-Meier survival curve ("still not succeeded") counts
    every episode: a policy that rarely succeeds but succeeds fast does not look fastest, unlike the
    success-only mean. With every failure censored at the horizon it equals the mean of
    ``min(time, horizon)``.

    Raises:
        ValueError: empty input, mismatched lengths, negative or non-finite times, horizon <= 0.
    """
    t = np.asarray(times, dtype=np.float64).reshape(-1)
    e = np.asarray(events, dtype=bool).reshape(-1)
    if t.size == 0 or t.size != e.size:
        raise ValueError(f"need one event flag per time, got {t.size} times and {e.size} flags")
    if not np.all(np.isfinite(t)) or np.any(t < 0):
        raise ValueError("times must be finite and >= 0")
    if not (math.isfinite(horizon) and horizon > 0):
        raise ValueError(f"horizon must be positive, got {horizon}")
    survival, area, last_t = 1.0, 0.0, 0.0
    for ti in np.unique(t[e & (t <= horizon)]):
        area += survival * (ti - last_t)
        at_risk = int(np.sum(t >= ti))
        survival *= 1.0 - int(np.sum((t == ti) & e)) / at_risk
        last_t = ti
    return float(area + survival * (horizon - last_t))
