"""Train a chunk policy on a collected dataset; writes ``<name>.pt`` (weights) + ``<name>.json`` (the rest).

The JSON holds everything needed to use the weights: model kind and size, chunk length H, the
feature layout, the normalisation statistics, inference defaults, plus the training configuration,
dataset provenance and the logged losses. The loss curves are also written next to the weights as
``<name>.loss.csv`` and ``<name>.loss.png``. The configuration and its defaults (the shipped recipe) are
in lq_ros/training/recipe.py.
"""

from __future__ import annotations

import json
import math
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from lq_ros.core.safe_write import replacing, save_figure, write_text
from lq_ros.core.suite_constants import ACTION_DIM
from lq_ros.policies.learned.features import FeatureLayout, features, goal_slots
from lq_ros.training.dataset import read_frames
from lq_ros.training.recipe import TrainConfig


def _log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def _prepare_one(
    data: Path, horizon: int, target: str, joint_velocity: bool | None
) -> tuple[dict, FeatureLayout, np.ndarray, np.ndarray, np.ndarray]:
    info, cols = read_frames(data)
    layout = FeatureLayout.from_dict(info["layout"])
    if joint_velocity is not None:
        layout = replace(layout, joint_velocity=joint_velocity)
    goals = {int(k): v for k, v in info["goals"].items()}
    task = cols["task_index"].astype(np.int64)
    slot_of = {t: goal_slots(layout, g) for t, g in goals.items()}
    slots = np.array([slot_of[int(t)] for t in task], dtype=np.int64).reshape(-1, 2)
    feats = features(layout, cols["observation.state"], cols["observation.environment_state"], task, slots)
    if target == "plan":
        plan = cols["action.chunk"]
        if plan.shape[1] < horizon:
            raise ValueError(f"{data} stores {plan.shape[1]}-row plans, horizon {horizon} needs more")
        targets = plan[:, :horizon]
    else:
        ep, actions = cols["episode_index"], cols["action"]
        targets = np.empty((len(actions), horizon, ACTION_DIM), np.float32)
        starts = np.flatnonzero(np.r_[True, ep[1:] != ep[:-1]])
        ends = np.r_[starts[1:], len(ep)]
        for s, e in zip(starts, ends):
            idx = np.minimum(np.arange(s, e)[:, None] + np.arange(horizon)[None, :], e - 1)
            targets[s:e] = actions[idx]
    return info, layout, feats, targets.astype(np.float32), cols["episode_index"].astype(np.int64)


def prepare(
    data: list[Path], horizon: int, target: str, joint_velocity: bool | None = None
) -> tuple[list[dict], FeatureLayout, np.ndarray, np.ndarray, np.ndarray]:
    """(infos, layout, features (N, F), chunk targets (N, H, 7), episode id (N,)) of one or more datasets.

    ``joint_velocity`` overrides the datasets' layout flag (None: keep it).
    """
    if not data:
        raise ValueError("no dataset given")
    infos, parts, layout, offset = [], [], None, 0
    for d in data:
        info, lay, feats, targets, episode = _prepare_one(Path(d), horizon, target, joint_velocity)
        if layout is not None and lay != layout:
            raise ValueError(f"{d}: feature layout {lay} differs from {layout} of {data[0]}")
        layout = lay
        infos.append(info)
        parts.append((feats, targets, episode + offset))
        offset += int(episode.max()) + 1
    assert layout is not None
    feats, targets, episode = (np.concatenate(p) for p in zip(*parts))
    return infos, layout, feats, targets, episode


def executed_prefixes(data: list[Path], rows: int) -> np.ndarray:
    """(N, rows, 7): the actions executed at frames t .. t + rows - 1 of each frame's episode (``action.executed``,
    padded with the episode's last one), in the order of :func:`prepare`'s frames."""
    out = []
    for d in data:
        _, cols = read_frames(Path(d))
        ep, executed = cols["episode_index"], cols["action.executed"]
        starts = np.flatnonzero(np.r_[True, ep[1:] != ep[:-1]])
        ends = np.repeat(np.r_[starts[1:], len(ep)], np.diff(np.r_[starts, len(ep)]))
        idx = np.minimum(np.arange(len(ep))[:, None] + np.arange(rows)[None, :], ends[:, None] - 1)
        out.append(executed[idx])
    return np.concatenate(out).astype(np.float32)


def successful_frames(data: list[Path]) -> np.ndarray:
    """(N,) bool: the frame belongs to an episode that ended in success (frames in :func:`prepare`'s order)."""
    out = []
    for d in data:
        _, cols = read_frames(Path(d))
        ep, success = cols["episode_index"], cols["next.success"].astype(bool)
        ended = np.zeros(int(ep.max()) + 1, bool)
        np.logical_or.at(ended, ep, success)
        out.append(ended[ep])
    return np.concatenate(out)


def delay_batch(prefix, horizon: int, delay_max: int, gen):
    """Training-time RTC for one batch of normalised executed prefixes (B, delay_max, 7): d drawn per sample in
    0..delay_max -> (conditioning (B, C) as delay.conditioning builds it, row mask (B, H): rows >= d, d (B,))."""
    import torch

    d = torch.randint(0, delay_max + 1, (prefix.shape[0],), generator=gen)
    keep = (torch.arange(delay_max)[None, :] < d[:, None]).float()
    one_hot = torch.nn.functional.one_hot(d, delay_max + 1).float()
    cond = torch.cat([one_hot, (prefix * keep[..., None]).flatten(1)], dim=1)
    mask = (torch.arange(horizon)[None, :] >= d[:, None]).float()
    return cond, mask, d


def with_prefix(targets, prefix, mask):
    """Chunk targets (B, H, 7) whose rows < d are the executed prefix (what the model is given, fed clean)."""
    import torch

    rows = prefix.shape[1]
    head = torch.where(mask[:, :rows, None] > 0, targets[:, :rows], prefix)
    return torch.cat([head, targets[:, rows:]], dim=1)


def find_init(init_from: str, out: Path) -> Path:
    """The checkpoint JSON to fine-tune from: a path, else a name in ``out``, else a shipped name."""
    from lq_ros.policies.learned.chunk_policy import resolve_weights

    path = Path(init_from)
    if path.suffix in (".json", ".pt") or len(path.parts) > 1:
        return path.with_suffix(".json")
    local = Path(out) / f"{init_from}.json"
    return local if local.is_file() else resolve_weights(init_from)


def _expand_input(state: dict, kind: str, extra: int) -> dict:
    """A naive checkpoint's state dict for a model with ``extra`` conditioning inputs: their weights start at 0."""
    import torch

    key = "inp.weight" if kind == "oft" else "obs.weight"
    w = state[key]
    return {**state, key: torch.cat([w, torch.zeros(w.shape[0], extra, dtype=w.dtype)], dim=1)}


def _stats(x: np.ndarray, floor: float) -> tuple[np.ndarray, np.ndarray]:
    mean = x.mean(axis=0)
    std = x.std(axis=0)
    # A (near-)constant input carries no information: scale 1 instead of blowing it up.
    return mean.astype(np.float32), np.where(std < floor, 1.0, std).astype(np.float32)


def train(cfg: TrainConfig, data: list[Path], out: Path) -> dict:
    """Train, write the checkpoint pair into ``out``; returns the JSON content."""
    import torch

    from lq_ros.core.run_config import versions
    from lq_ros.policies.learned.delay import conditioning_dim
    from lq_ros.policies.learned.networks import CHECKPOINT_FORMAT, build_model

    torch.set_num_threads(cfg.threads)
    torch.manual_seed(cfg.seed)
    t_start = time.perf_counter()
    infos, layout, feats, targets, episode = prepare(
        [Path(d) for d in data], cfg.horizon, cfg.target, cfg.joint_velocity
    )
    if cfg.successful_only:
        keep = successful_frames([Path(d) for d in data])
        feats, targets, episode = feats[keep], targets[keep], episode[keep]
        _log(f"successful episodes only: {int(keep.sum())} of {len(keep)} frames")
    rng = np.random.default_rng(cfg.seed)
    episodes = np.unique(episode)
    n_val = int(round(cfg.val_fraction * len(episodes))) if len(episodes) > 1 else 0
    val_eps = rng.choice(episodes, size=n_val, replace=False) if n_val else np.array([], np.int64)
    is_val = np.isin(episode, val_eps)
    init = None
    if cfg.init_from:
        init_path = find_init(cfg.init_from, out)
        init = json.loads(init_path.read_text())
        if (init["kind"], init["horizon"], init["layout"]) != (cfg.policy, cfg.horizon, layout.to_dict()):
            raise ValueError(f"{init_path}: a {init['kind']} H={init['horizon']} checkpoint of another layout")
        if int(init.get("delay", {}).get("delay_max", 0)):
            raise ValueError(f"{init_path}: fine-tuning starts from a naive checkpoint")
        # The initial weights work in their own normalisation: keep it.
        stats = init["stats"]
        f_mean, f_std, a_mean, a_std = (
            np.asarray(stats[k], np.float32) for k in ("feature_mean", "feature_std", "action_mean", "action_std")
        )
    else:
        f_mean, f_std = _stats(feats[~is_val], 1e-4)
        flat = targets[~is_val].reshape(-1, ACTION_DIM)
        a_mean, a_std = _stats(flat, 1e-4)
    x = torch.from_numpy((feats - f_mean) / f_std)
    y = torch.from_numpy((targets - a_mean) / a_std)
    extra = conditioning_dim(cfg.delay_max)
    prefix = None
    if cfg.delay_max:
        executed = executed_prefixes([Path(d) for d in data], cfg.delay_max)
        executed = executed[keep] if cfg.successful_only else executed
        prefix = torch.from_numpy((executed - a_mean) / a_std)
    train_idx = torch.from_numpy(np.flatnonzero(~is_val))
    val_idx = torch.from_numpy(np.flatnonzero(is_val))
    _log(f"{len(episodes)} episodes ({n_val} held out), {len(train_idx)}/{len(val_idx)} train/val frames")

    model = build_model(cfg.policy, layout.feature_dim + extra, cfg.horizon, cfg.width, cfg.depth, cfg.dropout)
    if init is not None:
        state = torch.load(init_path.with_name(init["weights_file"]), map_location="cpu", weights_only=True)
        model.load_state_dict(_expand_input({k: v.float() for k, v in state.items()}, cfg.policy, extra))
    n_params = sum(p.numel() for p in model.parameters())
    params = list(model.parameters())
    if cfg.freeze_base:
        # Only the first layer's columns of the conditioning inputs for d >= 1 learn (the d = 0 slot and the
        # features' columns keep their gradient at zero; Adam then leaves them exactly unchanged).
        first = (model.inp if cfg.policy == "oft" else model.obs).weight
        for p in model.parameters():
            p.requires_grad_(p is first)
        trainable = torch.zeros_like(first)
        trainable[:, layout.feature_dim + 1 :] = 1.0
        first.register_hook(lambda g: g * trainable)
        params = [first]
    opt = torch.optim.AdamW(params, lr=cfg.lr, weight_decay=0.0 if cfg.freeze_base else cfg.weight_decay)

    def lr_at(step: int) -> float:
        if step < cfg.warmup_steps:
            return cfg.lr * (step + 1) / cfg.warmup_steps
        frac = (step - cfg.warmup_steps) / max(cfg.steps - cfg.warmup_steps, 1)
        return cfg.lr * 0.5 * (1 + math.cos(math.pi * min(frac, 1.0)))

    gen = torch.Generator().manual_seed(cfg.seed)
    val_gen_seed = cfg.seed + 1
    # The averaged copy (or the model itself without EMA) is what is validated and saved.
    averaged = torch.optim.swa_utils.AveragedModel(
        model, multi_avg_fn=torch.optim.swa_utils.get_ema_multi_avg_fn(cfg.ema)
    ) if cfg.ema > 0 else None  # fmt: skip
    final = averaged.module if averaged is not None else model

    def val_loss() -> float | None:
        if len(val_idx) == 0:
            return None
        final.eval()
        g = torch.Generator().manual_seed(val_gen_seed)  # the same noise every time: comparable numbers
        with torch.no_grad():
            losses = [loss_of(final, val_idx[i : i + 4096], g).item() for i in range(0, len(val_idx), 4096)]
        model.train()
        return float(np.mean(losses))

    def loss_of(net, idx, g, noise: float = 0.0):
        xb, yb = x[idx], y[idx]
        if noise > 0:
            xb = xb + noise * torch.randn(xb.shape, generator=g)
        if prefix is None:
            return net.loss(xb, yb, g)
        cond, mask, _ = delay_batch(prefix[idx], cfg.horizon, cfg.delay_max, g)
        return net.loss(torch.cat([xb, cond], dim=1), with_prefix(yb, prefix[idx], mask), g, mask)

    log, running = [], []
    model.train()
    for step in range(cfg.steps):
        for group in opt.param_groups:
            group["lr"] = lr_at(step)
        batch = train_idx[torch.randint(len(train_idx), (cfg.batch_size,), generator=gen)]
        loss = loss_of(model, batch, gen, cfg.feature_noise)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(params, 1.0)
        opt.step()
        if averaged is not None:
            averaged.update_parameters(model)
        running.append(loss.item())
        if (step + 1) % cfg.log_every == 0 or step + 1 == cfg.steps:
            entry = {"step": step + 1, "train_loss": float(np.mean(running)), "val_loss": val_loss(),
                     "wall_s": round(time.perf_counter() - t_start, 1)}  # fmt: skip
            running = []
            log.append(entry)
            _log(json.dumps(entry))

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    name = cfg.run_name(layout.suite)
    weights = out / f"{name}.pt"
    with replacing(weights, binary=True) as f:  # never through a link (as every file written in --out)
        torch.save(final.state_dict(), f)
    write_loss_curves(out / name, log, f"{name}: {cfg.policy}, H={cfg.horizon}, {n_params} parameters")
    meta = {
        "format": CHECKPOINT_FORMAT,
        "kind": cfg.policy,
        "horizon": cfg.horizon,
        "width": cfg.width,
        "depth": cfg.depth,
        "weights_file": weights.name,
        "layout": layout.to_dict(),
        "stats": {
            "feature_mean": f_mean.tolist(),
            "feature_std": f_std.tolist(),
            "action_mean": a_mean.tolist(),
            "action_std": a_std.tolist(),
        },
        "inference": {"replan_steps": cfg.replan_steps, "flow_steps": cfg.flow_steps},
        **(
            {
                "delay": {
                    "delay_max": cfg.delay_max,
                    "method": "training-time RTC: d drawn per sample in 0..delay_max, conditioned on d and the d "
                    "executed actions after the frame, loss on rows d.. only",
                    "init_from": None
                    if init is None
                    else {"name": init_path.stem, "weights_md5": _md5(init_path, init)},
                }
            }
            if cfg.delay_max
            else {}
        ),
        "train_config": cfg.to_dict(),
        "metrics": {
            "params": n_params,
            "train_wall_s": round(time.perf_counter() - t_start, 1),
            "final_train_loss": log[-1]["train_loss"],
            "final_val_loss": log[-1]["val_loss"],
            "log": log,
        },
        "dataset": {
            "paths": [str(d) for d in data],
            "episodes": int(len(episodes)),
            "frames": int(len(feats)),
            "sources": [
                {k: info.get(k) for k in ("total_episodes", "total_frames", "collect_config", "collection", "versions")}
                for info in infos
            ],
        },
        "versions": versions(),
    }
    write_text(out / f"{name}.json", json.dumps(meta, indent=1))
    _log(f"wrote {weights} ({weights.stat().st_size / 1e6:.2f} MB, {n_params} parameters)")
    return meta


def _md5(path: Path, meta: dict) -> str:
    import hashlib

    return hashlib.md5(path.with_name(meta["weights_file"]).read_bytes()).hexdigest()


def write_loss_curves(stem: Path, log: list[dict], title: str) -> None:
    """``<stem>.loss.csv`` (step, train_loss, val_loss, wall_s) and ``<stem>.loss.png`` (log-scale plot)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    keys = ("step", "train_loss", "val_loss", "wall_s")
    lines = [",".join(keys)] + [",".join("" if e[k] is None else f"{e[k]:.6g}" for k in keys) for e in log]
    write_text(stem.with_name(stem.name + ".loss.csv"), "\n".join(lines) + "\n")
    fig, ax = plt.subplots(figsize=(6, 3.5), dpi=80)
    steps = [e["step"] for e in log]
    marker = "o" if len(log) < 10 else None  # a short log is a few points: show them
    ax.plot(steps, [e["train_loss"] for e in log], label="train", marker=marker)
    if any(e["val_loss"] is not None for e in log):
        ax.plot(steps, [e["val_loss"] for e in log], label="validation (held-out episodes)", marker=marker)
    ax.set_yscale("log")
    ax.set_xlabel("step")
    ax.set_ylabel("loss (normalised units)")
    ax.set_title(title, fontsize=9)
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    save_figure(fig, stem.with_name(stem.name + ".loss.png"))
    plt.close(fig)
