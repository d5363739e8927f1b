"""Two small chunk models on state features (torch, CPU).

* ``ChunkRegressor`` (OFT-like): one MLP decodes all H actions of a chunk in parallel; trained with L1.
* ``FlowChunkModel`` (pi0-like): a velocity field over the whole (H, 7) chunk, conditioned on the
  features and the flow time; trained with flow matching (x_t = (1-t) noise + t actions, target
  actions - noise), sampled with a few Euler steps from seeded Gaussian noise (``integrate``; an
  optional per-step hook can steer the integration, e.g. real-time-chunking guidance towards a given
  action prefix).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch
from torch import nn

from lq_ros.core.suite_constants import ACTION_DIM

#: Version of the ``<name>.json`` + ``<name>.pt`` checkpoint pair (train.py writes it, policy.py checks it).
#: 2: observation.state with joint velocities, the goal object's orientation in the goal features.
CHECKPOINT_FORMAT = 2

#: ``hook(x, t, v) -> x``: called after every Euler step with the chunk ``x`` (B, H, 7) reached at flow
#: time ``t`` (float) and the velocity ``v`` just used; returns the chunk to continue from.
FlowHook = Callable[[torch.Tensor, float, torch.Tensor], torch.Tensor]


class _Block(nn.Module):
    """Pre-norm residual MLP block."""

    def __init__(self, width: int, dropout: float = 0.0) -> None:
        super().__init__()
        self.net = nn.Sequential(nn.LayerNorm(width), nn.Linear(width, width), nn.GELU(), nn.Linear(width, width))
        self.drop = nn.Dropout(dropout)  # no parameters: checkpoints load with or without it

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + self.drop(self.net(x))


class ChunkRegressor(nn.Module):
    def __init__(self, feature_dim: int, horizon: int, width: int = 256, depth: int = 3, dropout: float = 0.0) -> None:
        super().__init__()
        self.horizon = horizon
        self.inp = nn.Linear(feature_dim, width)
        self.blocks = nn.Sequential(*(_Block(width, dropout) for _ in range(depth)))
        self.out = nn.Sequential(nn.LayerNorm(width), nn.Linear(width, horizon * ACTION_DIM))

    def forward(self, feats: torch.Tensor) -> torch.Tensor:
        """(B, F) normalised features -> (B, H, 7) normalised actions."""
        return self.out(self.blocks(self.inp(feats))).view(-1, self.horizon, ACTION_DIM)

    def loss(
        self,
        feats: torch.Tensor,
        actions: torch.Tensor,
        gen: torch.Generator | None = None,
        mask: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """L1; ``mask`` (B, H), optional: rows weighted 0 (a given prefix) do not count (training-time RTC)."""
        err = (self(feats) - actions).abs()
        return err.mean() if mask is None else masked_mean(err, mask)


def masked_mean(err: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Mean of ``err`` (B, H, 7) over the rows ``mask`` (B, H) keeps."""
    return (err * mask[..., None]).sum() / (mask.sum().clamp(min=1) * err.shape[-1])


def _time_embedding(t: torch.Tensor, dim: int) -> torch.Tensor:
    """Sinusoidal embedding of flow time t in [0, 1], (B,) -> (B, dim)."""
    half = dim // 2
    # Frequencies from 1 to 100 half-turns over the unit interval: resolves t to ~0.01.
    freqs = math.pi * torch.exp(torch.linspace(0.0, math.log(100.0), half, dtype=t.dtype))
    ang = t[:, None] * freqs[None, :]
    return torch.cat([ang.sin(), ang.cos()], dim=-1)


class FlowChunkModel(nn.Module):
    def __init__(
        self, feature_dim: int, horizon: int, width: int = 256, depth: int = 3, dropout: float = 0.0, time_dim: int = 64
    ) -> None:
        super().__init__()
        self.horizon = horizon
        self.time_dim = time_dim
        self.obs = nn.Linear(feature_dim, width)
        self.act = nn.Linear(horizon * ACTION_DIM, width)
        self.time = nn.Sequential(nn.Linear(time_dim, width), nn.GELU(), nn.Linear(width, width))
        self.blocks = nn.Sequential(*(_Block(width, dropout) for _ in range(depth)))
        self.out = nn.Sequential(nn.LayerNorm(width), nn.Linear(width, horizon * ACTION_DIM))

    def velocity(self, feats: torch.Tensor, x_t: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        """Velocity (B, H, 7) at chunk x_t (B, H, 7), flow time t (B,)."""
        h = self.obs(feats) + self.act(x_t.flatten(1)) + self.time(_time_embedding(t, self.time_dim))
        return self.out(self.blocks(h)).view(-1, self.horizon, ACTION_DIM)

    def loss(
        self,
        feats: torch.Tensor,
        actions: torch.Tensor,
        gen: torch.Generator | None = None,
        mask: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """Flow matching. ``mask`` (B, H), optional (training-time RTC): the rows weighted 0 are the given prefix,
        fed clean (as at t = 1) in x_t and left out of the loss."""
        noise = torch.randn(actions.shape, generator=gen)
        t = torch.rand(actions.shape[0], generator=gen)
        x_t = (1 - t)[:, None, None] * noise + t[:, None, None] * actions
        if mask is None:
            return ((self.velocity(feats, x_t, t) - (actions - noise)) ** 2).mean()
        x_t = torch.where(mask[..., None] > 0, x_t, actions)
        return masked_mean((self.velocity(feats, x_t, t) - (actions - noise)) ** 2, mask)

    @torch.no_grad()
    def sample(
        self, feats: torch.Tensor, noise: torch.Tensor, steps: int, hook: FlowHook | None = None
    ) -> torch.Tensor:
        """Chunk (B, H, 7) at t=1 integrated from ``noise`` at t=0 (see ``integrate``)."""
        return integrate(self.velocity, feats, noise, steps, hook)


def integrate(
    velocity: Callable[[torch.Tensor, torch.Tensor, torch.Tensor], torch.Tensor],
    feats: torch.Tensor,
    noise: torch.Tensor,
    steps: int,
    hook: FlowHook | None = None,
) -> torch.Tensor:
    """Euler integration of ``velocity(feats, x_t, t)`` from ``noise`` (B, H, 7) at t=0 to t=1 in ``steps`` steps.

    The single place a flow chunk is generated. ``hook`` (optional) sees the chunk after every step and
    may replace it; this is where real-time-chunking guidance (pulling the already-committed prefix of
    the chunk towards the actions still being executed) would go. Without a hook the result depends
    only on (feats, noise, steps).
    """
    if steps < 1:
        raise ValueError(f"steps must be >= 1, got {steps}")
    x = noise
    dt = 1.0 / steps
    for k in range(steps):
        t = torch.full((x.shape[0],), k * dt)
        v = velocity(feats, x, t)
        x = x + dt * v
        if hook is not None:
            x = hook(x, (k + 1) * dt, v)
    return x


MODELS = {"oft": ChunkRegressor, "flow": FlowChunkModel}


def build_model(kind: str, feature_dim: int, horizon: int, width: int, depth: int, dropout: float = 0.0) -> nn.Module:
    if kind not in MODELS:
        raise ValueError(f"unknown model kind {kind!r}; known: {', '.join(MODELS)}")
    return MODELS[kind](feature_dim, horizon, width=width, depth=depth, dropout=dropout)
