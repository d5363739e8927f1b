"""Analytic tests for lq_ros.scoring.metrics (pure numpy; no ROS needed)."""

from __future__ import annotations

import numpy as np
import pytest

from lq_ros.scoring import metrics as m

DT = 0.05  # 20 Hz LIBERO control period


def _reference_profile() -> tuple[np.ndarray, float]:
    t = np.arange(-1, 1, 0.01)
    return np.exp(-5 * t**2), 100.0


# ------------------------------------------------------------------ jerk


def test_cubic_path_has_constant_jerk():
    c = np.array([0.3, -1.2, 2.5])
    t = np.arange(40) * DT
    pos = c[None, :] * t[:, None] ** 3
    expected = 6.0 * np.linalg.norm(c)
    norms = m.jerk_norms(pos, DT)
    assert norms.shape == (37,)
    np.testing.assert_allclose(norms, expected, rtol=1e-9)
    assert m.jerk_mean(pos, DT) == pytest.approx(expected, rel=1e-9)
    assert m.jerk_p90(pos, DT) == pytest.approx(expected, rel=1e-9)


def test_quadratic_path_has_zero_jerk_and_dt_scaling():
    t = np.arange(10) * DT
    pos = np.stack([t**2, 2 * t**2, 0 * t], axis=1)
    assert m.jerk_mean(pos, DT) == pytest.approx(0.0, abs=1e-6)
    # a single step impulse in one sample: third difference pattern 1, -3, 3, -1 scaled by 1/dt^3
    pos = np.zeros((8, 3))
    pos[4, 0] = 1e-3
    norms = m.jerk_norms(pos, DT)
    np.testing.assert_allclose(norms, np.array([0, 1, 3, 3, 1]) * 1e-3 / DT**3, rtol=1e-12)
    assert m.jerk_p90(pos, DT) == pytest.approx(np.percentile(norms, 90))


def test_jerk_needs_four_samples():
    with pytest.raises(ValueError, match="at least 4"):
        m.jerk_mean(np.zeros((3, 3)), DT)
    with pytest.raises(ValueError, match="dt_s"):
        m.jerk_norms(np.zeros((5, 3)), 0.0)


# ------------------------------------------------------------------ energy


def test_energy_constant_torque_and_velocity():
    n = 50
    tau = np.array([1.0, -2.0, 3.0, 0.5, 0.0, 4.0, -1.0])
    qd = np.array([0.2, -0.1, 0.3, 1.0, 5.0, 0.1, 0.0])
    power = float(tau @ qd)
    assert power > 0
    e = m.energy_terms(np.tile(tau, (n, 1)), np.tile(qd, (n, 1)), DT)
    assert e.mech_j == pytest.approx(power * n * DT, rel=1e-12)
    assert e.elec_j == pytest.approx(0.0036 * float(tau @ tau) * n * DT, rel=1e-12)
    assert e.overhead_j == pytest.approx(85.0 * n * DT, rel=1e-12)
    assert e.total_j == pytest.approx(e.mech_j + e.elec_j + e.overhead_j, rel=1e-12)
    assert e.per_step_j == pytest.approx(e.total_j / n, rel=1e-12)
    assert e.n_steps == n


def test_energy_negative_power_gives_zero_mech():
    n = 20
    tau = np.array([2.0, 1.0])
    qd = np.array([-1.0, -0.5])
    e = m.energy_terms(np.tile(tau, (n, 1)), np.tile(qd, (n, 1)), DT, elec_coeff=0.01, overhead_w=10.0)
    assert e.mech_j == 0.0
    assert e.elec_j == pytest.approx(0.01 * 5.0 * n * DT)
    assert e.overhead_j == pytest.approx(10.0 * n * DT)


def test_energy_rejects_mismatched_shapes():
    with pytest.raises(ValueError):
        m.energy_terms(np.zeros((5, 7)), np.zeros((5, 6)), DT)
    with pytest.raises(ValueError):
        m.energy_terms(np.zeros((0, 7)), np.zeros((0, 7)), DT)


# ------------------------------------------------------------------ EE-Osc, path length


def test_ee_osc_stationary_tail_is_zero():
    moving = np.cumsum(np.full((30, 3), 0.01), axis=0)
    pos = np.vstack([moving, np.repeat(moving[-1:], 10, axis=0)])
    assert m.ee_oscillation(pos, window=10) == pytest.approx(0.0, abs=1e-15)
    assert m.ee_oscillation(pos, window=11) > 0.0  # the window really is the last K samples


def test_ee_osc_circle_gives_radius():
    r, k = 0.02, 12
    a = 2 * np.pi * np.arange(k) / k
    circle = np.stack([0.4 + r * np.cos(a), -0.1 + r * np.sin(a), np.full(k, 0.9)], axis=1)
    pos = np.vstack([np.zeros((5, 3)), circle])
    assert m.ee_oscillation(pos, window=k) == pytest.approx(r, rel=1e-12)
    # fewer samples than the window: uses all of them
    assert m.ee_oscillation(circle, window=100) == pytest.approx(r, rel=1e-12)
    assert m.DEFAULT_OSC_WINDOW == 10
    with pytest.raises(ValueError):
        m.ee_oscillation(np.zeros((0, 3)))


def test_trajectory_length_line_and_square():
    line = np.linspace([0, 0, 0], [0.3, 0.4, 0.0], 11)
    assert m.trajectory_length(line) == pytest.approx(0.5, rel=1e-12)
    s = 0.1
    square = np.array([[0, 0, 0], [s, 0, 0], [s, s, 0], [0, s, 0], [0, 0, 0]])
    assert m.trajectory_length(square) == pytest.approx(4 * s, rel=1e-12)
    assert m.trajectory_length(square[:1]) == 0.0


def test_speed_profile():
    pos = np.stack([np.arange(5) * 0.01, np.zeros(5), np.zeros(5)], axis=1)
    np.testing.assert_allclose(m.speed_profile(pos, DT), np.full(4, 0.2))


# ------------------------------------------------------------------ SPARC / LDLJ


def test_sparc_reference_value():
    v, fs = _reference_profile()
    assert m.sparc(v, fs) == pytest.approx(-1.41403, abs=1e-5)


def test_dimensionless_jerk_and_ldlj_reference_values():
    v, fs = _reference_profile()
    assert m.dimensionless_jerk(v, fs) == pytest.approx(-335.74684, abs=1e-5)
    assert m.ldlj(v, fs) == pytest.approx(-5.81636, abs=1e-5)


def test_smoothness_orders_jerky_profile_lower():
    v, fs = _reference_profile()
    t = np.arange(v.size) / fs
    jerky = v * (1 + 0.2 * np.sin(2 * np.pi * 4 * t))
    assert m.sparc(jerky, fs) < m.sparc(v, fs)
    assert m.ldlj(jerky, fs) < m.ldlj(v, fs)
    with pytest.raises(ValueError):
        m.sparc(np.zeros(50), fs)
    with pytest.raises(ValueError):
        m.ldlj(np.zeros(50), fs)


# ------------------------------------------------------------------ sampling


def test_check_uniform_accepts_uniform_and_detects_gap():
    t = 3.0 + np.arange(40) * DT
    assert m.check_uniform(t, DT) is None
    t_gap = np.concatenate([t[:5], t[7:]])  # drop two samples after t[4] = 3.2 s
    reason = m.check_uniform(t_gap, DT)
    assert reason is not None
    assert "gap of 0.150 s at t=3.200 s (expected 0.050 s)" in reason
    assert m.check_uniform(np.array([0.0, 0.05, 0.04]), DT) is not None
    assert m.check_uniform(np.array([0.0]), DT) is not None


def test_resample_uniform_reproduces_linear_function():
    rng = np.random.default_rng(1)
    t = np.sort(rng.uniform(0.0, 2.0, 37))
    t[0], t[-1] = 0.0, 2.0
    vals = np.stack([3.0 * t - 1.0, -0.5 * t + 2.0], axis=1)
    t_new, v_new = m.resample_uniform(t, vals, DT)
    assert t_new.shape == (41,) and v_new.shape == (41, 2)
    np.testing.assert_allclose(np.diff(t_new), DT, rtol=1e-9)
    np.testing.assert_allclose(v_new[:, 0], 3.0 * t_new - 1.0, atol=1e-12)
    np.testing.assert_allclose(v_new[:, 1], -0.5 * t_new + 2.0, atol=1e-12)
    assert m.check_uniform(t_new, DT) is None
    _, v1 = m.resample_uniform(t, vals[:, 0], DT)
    np.testing.assert_allclose(v1, v_new[:, 0])


def test_smoothness_is_undefined_without_movement():
    still = np.full(40, 1e-5)  # simulator noise of an arm that never moved, m/s
    for fn in (m.sparc, m.ldlj):
        with pytest.raises(ValueError, match="did not move"):
            fn(still, 20.0)
    with pytest.raises(ValueError, match="zero second difference"):
        m.ldlj(np.full(30, 0.25), 20.0)  # constant speed: DJ = 0, its log undefined


def test_ee_osc_detrended_removes_straight_travel():
    k = np.arange(10)[:, None]
    travel = np.array([0.0, 0.0, 1.0]) + 0.005 * k * np.array([1.0, 0.5, 0.0])  # 5 mm/step straight line
    assert m.ee_oscillation(travel) > 0.01 and m.ee_oscillation_detrended(travel) == pytest.approx(0.0, abs=1e-12)
    wobble = travel + 0.002 * np.where(k % 2, 1.0, -1.0) * np.array([0.0, 0.0, 1.0])  # +-2 mm in z
    assert m.ee_oscillation_detrended(wobble) == pytest.approx(0.002, rel=0.05)


def test_energy_from_integrals_sums_the_intervals():
    terms = m.energy_from_integrals([1.0, 2.0], [100.0, 300.0], [0.05, 0.05], steps=2, elec_coeff=0.01, overhead_w=10.0)
    assert (terms.mech_j, terms.elec_j, terms.overhead_j) == pytest.approx((3.0, 4.0, 1.0))
    assert terms.per_step_j == pytest.approx(4.0)
    with pytest.raises(ValueError):
        m.energy_from_integrals([-1.0], [0.0], [0.05], steps=1)


def test_restricted_mean_time_kaplan_meier():
    # Censored before the horizon too: S drops to 2/3 at 2, to 1/3 at 3, stays past the censoring at 5.
    assert m.restricted_mean_time([2, 3, 5], [True, True, False], 10.0) == pytest.approx(2 + 2 / 3 + 7 / 3)
    # Everything censored at the horizon: the mean of min(t, horizon).
    assert m.restricted_mean_time([2, 11, 11], [True, False, False], 11.0) == pytest.approx(8.0)
