"""The training recipe of the shipped weights, in one place: ``TrainConfig``'s defaults.

``TrainConfig(policy=KIND, horizon=H)`` with every other field at its default is the configuration the
shipped ``<KIND>_c<H>_<suite>`` weights were trained with (each records it as ``train_config`` in its
JSON), and ``lq train --policy KIND --chunk H`` with no other option builds exactly that configuration
(its option defaults are read from here). The fields that differ between the two kinds (chunk length,
steps, EMA, actions per chunk) default to a sentinel that ``__post_init__`` replaces with the kind's value
from :data:`KIND_RECIPE`, so the stored ``train_config`` always holds the values that were used.

Pure Python (no numpy/torch): the CLI imports it at start-up.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

KINDS = ("oft", "flow")
#: Per kind: chunk length H, optimiser steps and EMA decay of the shipped recipe (docs/design/learned_policies.md,
#: "The shipped recipe"). ``replan_steps`` (actions run per chunk) defaults to H for ``oft`` (open loop, the
#: whole chunk) and H // 2 for ``flow`` (see :func:`default_replan_steps`).
KIND_RECIPE: dict[str, dict[str, float]] = {
    "oft": {"horizon": 8, "steps": 12000, "ema": 0.0},
    "flow": {"horizon": 10, "steps": 16000, "ema": 0.999},
}


def default_replan_steps(policy: str, horizon: int) -> int:
    """Actions executed per chunk stored with the weights: the whole chunk (oft), half of it (flow)."""
    return max(horizon // 2, 1) if policy == "flow" else horizon


@dataclass(frozen=True)
class TrainConfig:
    policy: str = "oft"  # "oft" | "flow"
    #: Chunk length H; 0: the kind's (KIND_RECIPE: oft 8, flow 10).
    horizon: int = 0
    width: int = 256
    depth: int = 4
    #: Optimiser steps; 0: the kind's (oft 12 000, flow 16 000).
    steps: int = 0
    batch_size: int = 256
    lr: float = 1e-3
    weight_decay: float = 1e-4
    warmup_steps: int = 200
    #: Regularisation against the small dataset: dropout in the MLP blocks, and Gaussian noise (std in
    #: normalised feature units) added to the training inputs.
    dropout: float = 0.0
    feature_noise: float = 0.0
    #: Exponential moving average of the weights (decay per step; 0: off; None: the kind's, oft 0 and
    #: flow 0.999). The averaged weights are the ones validated and saved.
    ema: float | None = None
    #: Joint velocities as inputs (overrides the dataset's layout; see features.FeatureLayout).
    joint_velocity: bool = False
    seed: int = 0
    #: Fraction of episodes held out for the validation loss.
    val_fraction: float = 0.05
    #: Chunk targets: "future" (the expert's labels of the next H frames, padded with the last one) or
    #: "plan" (the expert's open-loop plan from that frame; docs: what did not help).
    target: str = "future"
    #: Inference defaults stored with the weights: actions executed per chunk (0: default_replan_steps),
    #: flow integration steps.
    replan_steps: int = 0
    flow_steps: int = 10
    #: torch threads; 1 is fastest when other processes share the cores.
    threads: int = 1
    log_every: int = 500
    name: str = ""
    #: Delay-aware variant (training-time real-time chunking, lq_ros/policies/learned/delay.py): the model is
    #: also given d and the d executed actions that follow the frame, with d drawn per sample in 0..delay_max,
    #: and its loss covers rows d.. only. 0: the naive model (no conditioning). At most horizon - 1.
    delay_max: int = 0
    #: Fine-tune from this checkpoint (a name: looked up in the output folder first, then among the shipped
    #: weights; or a path): its weights (the conditioning inputs start at zero) and its normalisation. "": none.
    init_from: str = ""
    #: With ``init_from``: train only the conditioning inputs' first-layer weights (for d >= 1; weight decay off),
    #: the rest stays the initial checkpoint's, so at d = 0 the model is exactly the one it started from.
    freeze_base: bool = False
    #: Train on the frames of successful episodes only (a DAgger dataset collected with --keep-failures).
    successful_only: bool = False

    def __post_init__(self) -> None:
        if self.policy not in KINDS:
            raise ValueError(f"policy must be 'oft' or 'flow', got {self.policy!r}")
        kind = KIND_RECIPE[self.policy]
        if self.horizon == 0:
            object.__setattr__(self, "horizon", int(kind["horizon"]))
        if self.steps == 0:
            object.__setattr__(self, "steps", int(kind["steps"]))
        if self.ema is None:
            object.__setattr__(self, "ema", float(kind["ema"]))
        if self.replan_steps == 0 and self.horizon >= 1:
            object.__setattr__(self, "replan_steps", default_replan_steps(self.policy, self.horizon))
        if self.target not in ("plan", "future"):
            raise ValueError(f"target must be 'plan' or 'future', got {self.target!r}")
        for key in ("horizon", "width", "depth", "steps", "batch_size", "flow_steps", "threads", "log_every"):
            if getattr(self, key) < 1:
                raise ValueError(f"{key} must be >= 1, got {getattr(self, key)}")
        if not 1 <= self.replan_steps <= self.horizon:
            raise ValueError(f"replan_steps must be in 1..horizon={self.horizon}, got {self.replan_steps}")
        if not 0.0 <= self.ema < 1.0:
            raise ValueError(f"ema must be in [0, 1), got {self.ema}")
        if self.freeze_base and not (self.init_from and self.delay_max):
            raise ValueError("freeze_base needs init_from and delay_max (it trains the conditioning inputs only)")
        if not 0 <= self.delay_max < self.horizon:
            raise ValueError(f"delay_max must be in 0..horizon-1={self.horizon - 1}, got {self.delay_max}")

    def run_name(self, suite: str) -> str:
        """Checkpoint name: ``--name``, else ``<policy>_c<H>[_delay]_<suite>`` (the shipped naming)."""
        delay = "_delay" if self.delay_max else ""
        return self.name or f"{self.policy}_c{self.horizon}{delay}_{suite}"

    def to_dict(self) -> dict:
        """The resolved configuration, as stored in the weights' JSON (``train_config``).

        The fields added with the delay-aware variant (:data:`DELAY_FIELDS`) appear only when set: a naive
        configuration is recorded exactly as before they existed."""
        out = asdict(self)
        for key in DELAY_FIELDS:
            if out[key] == DELAY_FIELDS[key]:
                del out[key]
        return out


#: Fields of the delay-aware variant with their defaults (omitted from ``TrainConfig.to_dict`` at the default).
DELAY_FIELDS = {"delay_max": 0, "init_from": "", "freeze_base": False, "successful_only": False}


def parse_ids(spec: str) -> tuple[int, ...]:
    """``"0-9"``, ``"0,2,5"`` or ``"10-29,40"`` -> integers (``lq collect``'s task and init selections);
    ValueError if it is not such a selection."""
    out: list[int] = []
    try:
        if not str(spec).isascii():  # int() takes any script's digits: 0-9 only
            raise ValueError
        for part in str(spec).split(","):
            lo, sep, hi = part.strip().partition("-")
            out += range(int(lo), int(hi) + 1) if sep else [int(lo)]
    except ValueError:
        raise ValueError(f"expected integers like '0-9' or '0,2,5', got {spec!r}") from None
    if not out:
        raise ValueError(f"empty selection {spec!r}")
    return tuple(out)
