"""Real-time chunking (Black et al. 2025): guided inpainting of a flow-matching chunk against the executing prefix.

A flow policy integrates a velocity field v(x, t) from noise (t = 0) to a chunk (t = 1). While it infers, the
robot executes the first d actions of the old plan (d = the inference's latency ticks), and the old plan
goes on beyond them. RTC makes the new chunk agree with that plan: at every integration step it pulls the
chunk's *denoised estimate* x̂₁ = x + (1 - t) v(x, t) towards the target Y (the old plan, aligned so row i
is for the same tick) with per-row weights W, through the vector-Jacobian product of the estimate
(pseudo-inverse guidance, RTC's Algorithm 1; as in real-time-chunking-kinetix ``realtime_action``):

    e = (Y - x̂₁(x)) ⊙ W,   g = eᵀ ∂x̂₁/∂x,   x ← x + Δt (v + min(β, (1 - t)/t · 1/r²_t) g),
    1/r²_t = (t² + (1 - t)²) / (1 - t)²,     β: the maximum guidance weight (5, the kinetix default).

Weights (:func:`prefix_weights`, kinetix ``get_prefix_weights`` with start = d, end = L, the plan's length):
``exp`` (RTC, soft masking): 1 for i < d, then c_i (e^{c_i} - 1)/(e - 1) with c_i = (d - 1 - i)/(L - d + 1) + 1
decaying to 0 at L, 0 beyond (no plan there); ``linear``: c_i; ``hard`` (hard masking, the RTC paper's
ablation, kinetix ``zeros``): 1 for i < d, 0 elsewhere; ``ones``: 1 for i < L.

The module is torch-only at call time and knows nothing of a model: it takes the velocity function and the
Euler schedule, so any flow policy can use it. :func:`inpaint_chunk` is the one call a flow policy needs: it
normalises the executor's prefix (lq_ros.core.merge.ActionPrefix, in action units) like the policy's training
actions and samples the guided chunk.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from lq_ros.core.merge import ActionPrefix

#: Maximum guidance weight β (real-time-chunking-kinetix's default; LeRobot's RTC uses 10).
MAX_GUIDANCE = 5.0
SCHEDULES = ("exp", "linear", "hard", "ones")


def prefix_weights(delay: int, end: int, horizon: int, schedule: str = "exp") -> np.ndarray:
    """(horizon,) guidance weights of the rows of a chunk: see the module docstring.

    ``delay`` d: rows that execute while inferring (weight 1); ``end`` L: rows the old plan covers (weight 0
    from there on). ``end`` wins over ``delay`` (d > L: only the L planned rows guide).
    """
    if schedule not in SCHEDULES:
        raise ValueError(f"prefix schedule must be one of {', '.join(SCHEDULES)}, got {schedule!r}")
    end = max(0, min(int(end), horizon))
    start = min(max(0, int(delay)), end)
    i = np.arange(horizon, dtype=np.float64)
    if schedule == "ones":
        w = np.ones(horizon)
    elif schedule == "hard":
        w = (i < start).astype(np.float64)
    else:
        w = np.clip((start - 1 - i) / (end - start + 1) + 1, 0.0, 1.0)
        if schedule == "exp":
            w = w * np.expm1(w) / (math.e - 1)
    return np.where(i >= end, 0.0, w)


def guidance_weight(t: float, max_guidance: float = MAX_GUIDANCE) -> float:
    """min(β, (1 - t)/t · (t² + (1 - t)²)/(1 - t)²); β at t = 0."""
    if t <= 0.0:
        return max_guidance
    inv_r2 = (t**2 + (1 - t) ** 2) / (1 - t) ** 2
    return min(max_guidance, (1 - t) / t * inv_r2)


def guided_sample(
    velocity: Callable,
    noise,
    steps: int,
    target,
    weights,
    max_guidance: float = MAX_GUIDANCE,
):
    """Euler integration of ``velocity(x, t)`` from ``noise`` (B, H, D) at t = 0 to t = 1 in ``steps`` steps,
    guided towards ``target`` (B or 1, H, D; rows with weight 0 are ignored) with row ``weights`` (H,).

    The schedule equals the unguided sampler's (t_k = k / steps, x += Δt v), so with all weights 0 the result
    is the unguided chunk. Gradients flow only through ``velocity`` at each step (the result is detached).
    """
    import torch

    if steps < 1:
        raise ValueError(f"steps must be >= 1, got {steps}")
    w = torch.as_tensor(np.asarray(weights), dtype=noise.dtype).reshape(1, -1, 1)
    y = torch.as_tensor(target, dtype=noise.dtype)
    guided = bool(torch.any(w > 0))
    x = noise.detach()
    dt = 1.0 / steps
    for k in range(steps):
        t = k * dt
        if not guided:
            with torch.no_grad():
                x = x + dt * velocity(x, t)
            continue
        with torch.enable_grad():
            xg = x.detach().requires_grad_(True)
            v = velocity(xg, t)
            x1 = xg + (1.0 - t) * v
            err = ((y - x1) * w).detach()
            (correction,) = torch.autograd.grad(x1, xg, grad_outputs=err)
        x = (xg + dt * (v + guidance_weight(t, max_guidance) * correction)).detach()
    return x


def inpaint_chunk(
    velocity: Callable,
    noise,
    steps: int,
    prefix: ActionPrefix,
    action_mean,
    action_std,
    max_guidance: float = MAX_GUIDANCE,
):
    """The normalised chunk (1, H, D) a flow policy samples under real-time chunking.

    ``prefix.actions`` (L, D) in action units become the target (a - mean) / std of rows 0..min(L, H)-1,
    weighted by ``prefix_weights(prefix.delay, L, H, prefix.schedule)``; ``velocity(x, t)`` and ``noise``
    (1, H, D) are the policy's, in its normalised units. An empty prefix gives the unguided chunk.
    """
    import torch

    horizon = noise.shape[1]
    n = min(len(prefix.actions), horizon)
    target = np.zeros(tuple(noise.shape[1:]), dtype=np.float64)
    target[:n] = (prefix.actions[:n] - np.asarray(action_mean, dtype=np.float64)) / np.asarray(action_std, np.float64)
    weights = prefix_weights(prefix.delay, n, horizon, prefix.schedule)
    y = torch.as_tensor(target, dtype=noise.dtype)[None]
    return guided_sample(velocity, noise, steps, y, weights, max_guidance)
