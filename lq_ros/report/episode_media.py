"""Per-episode media for ``lq report``: a figure for every episode, replay videos for a few per cell.

Figures (lq_ros/report/episode_plot.py) need only the bag. Videos re-simulate the episode
(lq_ros/report/replay.py), which costs CPU (~0.1-0.25 s per tick for two 256 px cameras), so they are off
unless asked for: up to K per (policy, protocol, Δt_sim) cell, alternating successes and failures. Both are
cached: a file newer than its bag and made from that bag (``episodes/.sources.json``, the replay verdict's
``bag``) is kept; a report of another folder into the same ``--out`` never reuses a figure of a bag that only
shares its name. Paths stored in the episode table are relative to the report
folder, so links survive moving it.
"""

from __future__ import annotations

import hashlib
import html
import json
import math
import re
from collections.abc import Callable, Sequence
from pathlib import Path

import pandas as pd

from lq_ros.core.bounded_file import MANIFEST_MAX_BYTES, FileRefused, read_results_json
from lq_ros.core.safe_write import output_folder, write_text
from lq_ros.report.escape import md_link_target, md_text
from lq_ros.report.replay import DEFAULT_CAMERAS, DEFAULT_SIZE_PX, ReplayRefused

#: Columns added to the episode table: figure path, video path, replay verdict.
MEDIA_COLUMNS = ("plot", "video", "replay")
FIGURE_DIR = "episodes"
#: In FIGURE_DIR: figure file name -> the bag it was drawn from (resolved path), so the cache never takes a figure
#: of another bag of the same name (a report of another folder into the same --out).
FIGURE_SOURCES = ".sources.json"
VIDEO_DIR = "videos"
#: progress(stage, done, total): stage is "episode figures" (episodes) or "replay videos" (ticks).
Progress = Callable[[str, int, int], None]


def _bag_mtime(bag: Path) -> float:
    files = list(bag.glob("*.mcap")) + [bag / "metadata.yaml"]
    return max((f.stat().st_mtime for f in files if f.exists()), default=math.inf)


def _fresh(path: Path, bag: Path) -> bool:
    return path.exists() and path.stat().st_mtime >= _bag_mtime(bag)


def _bag_path(results_dir: Path, bag) -> Path | None:
    if not isinstance(bag, str) or not bag:
        return None
    path = results_dir / bag
    return path if (path / "metadata.yaml").exists() or any(path.glob("*.mcap")) else None


def _file_safe(text: str) -> str:
    """``text`` as a file name part: anything but letters, digits, '.', '_' and '-' becomes '_'."""
    return re.sub(r"[^A-Za-z0-9._-]", "_", text).strip(".") or "run"


def media_names(bags: dict, results_dir: Path, runs: dict | None = None) -> dict:
    """A file name stem per episode, unique in the report: the bag folder's name, prefixed with its run's name in
    a report of several runs (``runs``: index -> the ``run`` column; two runs' episodes often share a folder
    name, and a run's figure must never be another's), and where two bags still share it (``a/ep`` and ``b/ep``),
    that name with a hash of the bag's path below ``results_dir`` (stable across reports, so the cache of figures
    and videos still finds them)."""
    runs = runs or {}
    names = {}
    for i, bag in bags.items():
        if bag is None:
            continue
        run = runs.get(i)
        names[i] = f"{_file_safe(str(run))}__{bag.name}" if isinstance(run, str) and run else bag.name
    counts: dict[str, int] = {}
    for name in names.values():
        counts[name] = counts.get(name, 0) + 1
    out = {}
    for i, name in names.items():
        if counts[name] > 1:
            where = bags[i].relative_to(results_dir) if bags[i].is_relative_to(results_dir) else bags[i]
            name = f"{name}-{hashlib.sha256(str(where).encode()).hexdigest()[:10]}"
        out[i] = name
    return out


def pick_video_episodes(episodes: pd.DataFrame, k: int, cell_keys: Sequence[str]) -> list:
    """Index labels of up to ``k`` episodes per cell: success, failure, success, ... (errors never)."""
    if k <= 0 or episodes.empty:
        return []
    order = [c for c in ("suite", "task", "init", "seed") if c in episodes]
    picked = []
    for _, rows in episodes.groupby(list(cell_keys), dropna=False, sort=True):
        rows = rows.sort_values(order) if order else rows
        queues = [list(rows.index[rows["status"] == s]) for s in ("success", "failure")]
        while len([i for i in picked if i in rows.index]) < k and any(queues):
            for q in queues:
                if q and len([i for i in picked if i in rows.index]) < k:
                    picked.append(q.pop(0))
    return picked


def add_episode_media(
    episodes: pd.DataFrame,
    results_dir: Path,
    out_dir: Path,
    *,
    videos: int = 0,
    cell_keys: Sequence[str] = ("policy", "mode", "latency_s"),
    progress: Progress | None = None,
    cameras: tuple[str, ...] = DEFAULT_CAMERAS,
    size_px: int = DEFAULT_SIZE_PX,
) -> tuple[pd.DataFrame, list[str]]:
    """``episodes`` with MEDIA_COLUMNS filled in (None where there is none) and the warnings met on the way."""
    from lq_ros.report.episode_plot import write_episode_figure
    from lq_ros.report.replay import replay, write_sidecar

    results_dir, out_dir = Path(results_dir), Path(out_dir)
    out = episodes.copy()
    for col in MEDIA_COLUMNS:
        out[col] = None
    warnings: list[str] = []
    bags = {i: _bag_path(results_dir, b) for i, b in out.get("bag", pd.Series(dtype=object)).items()}
    todo = [i for i, b in bags.items() if b is not None]
    runs = out["run"].to_dict() if "run" in out else None
    names = media_names(bags, results_dir, runs)
    sources = _figure_sources(out_dir / FIGURE_DIR / FIGURE_SOURCES)
    known = dict(sources)
    for n, i in enumerate(todo):
        bag = bags[i]
        png = out_dir / FIGURE_DIR / f"{names[i]}.png"
        source = str(bag.resolve())
        try:
            if not (sources.get(png.name) == source and _fresh(png, bag)):
                sources.pop(png.name, None)
                write_episode_figure(bag, png)
            sources[png.name] = source
            out.at[i, "plot"] = f"{FIGURE_DIR}/{png.name}"
        except Exception as exc:  # noqa: BLE001 - one unreadable bag must not sink the report
            warnings.append(f"episode figure of {bag}: {type(exc).__name__}: {exc}")
        if progress:
            progress("episode figures", n + 1, len(todo))
    if sources != known and (out_dir / FIGURE_DIR).is_dir():  # (unchanged: left as it is, like the figures)
        write_text(out_dir / FIGURE_DIR / FIGURE_SOURCES, json.dumps(sources, indent=0, sort_keys=True))

    chosen = [i for i in pick_video_episodes(out, videos, cell_keys) if bags.get(i) is not None]
    steps = out.get("completion_steps", pd.Series(dtype=float))
    ticks = {i: int(steps[i]) if pd.notna(steps.get(i)) else 1 for i in chosen}
    total, done = sum(ticks.values()), 0
    if chosen:
        output_folder(out_dir / VIDEO_DIR, "video folder", follow=False)  # (in a report folder: never a link)
    for i in chosen:
        bag = bags[i]
        mp4 = out_dir / VIDEO_DIR / f"{names[i]}.mp4"
        verdict = mp4.with_suffix(".json")
        try:
            result = _cached_verdict(verdict, bag) if _fresh(mp4, bag) and _fresh(verdict, bag) else None
            if result is None:
                base = done

                def tick(k: int, _n: int, base: int = base) -> None:
                    if progress:
                        progress("replay videos", base + k, total)

                r = replay(bag.resolve(), video=mp4, cameras=cameras, size_px=size_px, on_tick=tick)
                write_sidecar(r, verdict)
                result = r.to_dict()
            out.at[i, "video"] = f"{VIDEO_DIR}/{mp4.name}"
            out.at[i, "replay"] = replay_verdict(result)
            if not result["equal"]:
                warnings.append(f"replay of {bag.name} differs from its bag: {out.at[i, 'replay']}")
        except ReplayRefused as exc:
            warnings.append(f"no video of {bag.name}: {exc}")
            out.at[i, "replay"] = "not replayable"
        done += ticks[i]
        if progress:
            progress("replay videos", done, total)
    return out, warnings


def _figure_sources(path: Path) -> dict[str, str]:
    """FIGURE_SOURCES of an earlier report ({} when there is none or it cannot be used: every figure is redrawn)."""
    try:
        sources = read_results_json(path, "figure index", max_bytes=MANIFEST_MAX_BYTES)
    except FileRefused:
        return {}
    if not isinstance(sources, dict):
        return {}
    return {k: v for k, v in sources.items() if isinstance(v, str)}


def _cached_verdict(path: Path, bag: Path) -> dict | None:
    """A replay's verdict written by an earlier report of ``bag``, or None (replayed again) when it cannot be used
    (another bag's, of the same name, included)."""
    try:
        result = read_results_json(path, "replay verdict")
    except FileRefused:
        return None
    if not isinstance(result, dict) or not isinstance(result.get("equal"), bool):
        return None
    if result.get("bag") != str(bag.resolve()):  # (add_episode_media replays the resolved path)
        return None
    d = result.get("divergence")
    numbers = isinstance(d, dict) and all(isinstance(d.get(k), int | float) for k in ("tick", "position_error_m"))
    return result if d is None or numbers else None


def replay_verdict(result: dict) -> str:
    """Short text of a replay result (ReplayResult.to_dict()): 'equal' or where it diverged."""
    if result.get("equal"):
        return "= bag"
    d = result.get("divergence")
    if d:
        return f"≠ bag from tick {d['tick']} ({d['position_error_m']:.2g} m)"
    return "≠ bag (outcome)"


# -- page fragments ---------------------------------------------------------------------------------


def _present(v) -> bool:
    return isinstance(v, str) and bool(v)


def table_columns(episodes: pd.DataFrame) -> list[str]:
    """The media columns present (the episode table keeps them; the pages turn them into links)."""
    return [c for c in MEDIA_COLUMNS if c in episodes]


def link_headers(table: pd.DataFrame) -> list[str]:
    """Headers of the link cells that html_cells / md_cells return for ``table``'s rows."""
    return [c for c in ("plot", "video") if c in table]


def html_cells(row) -> str:
    """The link cells of one episode row (double-quoted hrefs, relative to the report folder)."""
    e = html.escape
    cells = []
    if "plot" in row:
        cells.append(f'<a href="{e(row["plot"])}">plot</a>' if _present(row["plot"]) else "–")
    if "video" in row:
        if _present(row["video"]):
            cells.append(f'<a href="{e(row["video"])}">video</a> {e(str(row.get("replay") or ""))}')
        else:
            cells.append(e(str(row.get("replay") or "–")))
    return "".join(f"<td style='text-align:left'>{c}</td>" for c in cells)


def md_cells(row) -> list[str]:
    cells = []
    if "plot" in row:
        cells.append(f"[plot]({md_link_target(row['plot'])})" if _present(row["plot"]) else "–")
    if "video" in row:
        video = f"[video]({md_link_target(row['video'])}) {md_text(row.get('replay') or '')}"
        cells.append(video.strip() if _present(row["video"]) else "–")
    return cells


def _caption(row) -> str:
    parts = [f"{k} {row[k]}" for k in ("suite", "task", "init", "seed") if k in row and pd.notna(row[k])]
    status = row.get("status")
    steps = row.get("completion_steps")
    end = f"{status}" + (f" at tick {int(steps)}" if pd.notna(steps) else "")
    return " · ".join([*parts, end, f"replay {row.get('replay')}"])


def _cell_title(cell_keys: Sequence[str], cell) -> str:
    """'scripted · async · Δt_sim 0.2 s' (+ 'key value' for any other grouping key)."""
    cell = cell if isinstance(cell, tuple) else (cell,)
    parts = []
    for k, v in zip(cell_keys, cell, strict=True):
        if k in ("policy", "mode"):
            parts.append(str(v))
        elif k == "latency_s":
            parts.append(f"Δt_sim {v:g} s" if isinstance(v, int | float) else f"Δt_sim {v}")
        else:
            parts.append(f"{k} {v}")
    return " · ".join(parts)


def videos_html(episodes: pd.DataFrame, cell_keys: Sequence[str]) -> str:
    """A "Replay videos" section: per cell, its videos inline (empty string without videos)."""
    if "video" not in episodes or not episodes["video"].map(_present).any():
        return ""
    e = html.escape
    parts = ["<h2>Replay videos</h2><p>Re-simulated from each bag's recorded commands; the strip shows the tick, "
             "the command's source (colours as in the timeline: chunk, hold, underrun, rejected), chunk switches "
             "and the outcome. docs/guide/visualize.md explains them.</p>"]  # fmt: skip
    with_video = episodes[episodes["video"].map(_present)]
    for cell, rows in with_video.groupby(list(cell_keys), sort=True):
        parts.append(f"<h3>{e(_cell_title(cell_keys, cell))}</h3><div style='display:flex;flex-wrap:wrap;gap:12px'>")
        for _, r in rows.iterrows():
            parts.append(f'<figure style="margin:0"><video controls preload="metadata" src="{e(r["video"])}" '
                         f'style="max-width:560px"></video><figcaption style="font-size:12px">'
                         f'<a href="{e(r["video"])}">{e(_caption(r))}</a></figcaption></figure>')  # fmt: skip
        parts.append("</div>")
    return "\n".join(parts)


def videos_md(episodes: pd.DataFrame, cell_keys: Sequence[str]) -> list[str]:
    if "video" not in episodes or not episodes["video"].map(_present).any():
        return []
    lines = ["## Replay videos", ""]
    for cell, rows in episodes[episodes["video"].map(_present)].groupby(list(cell_keys), sort=True):
        lines.append("- " + md_text(_cell_title(cell_keys, cell)) + ": "
                     + ", ".join(f"[{md_text(_caption(r))}]({md_link_target(r['video'])})"
                                 for _, r in rows.iterrows()))  # fmt: skip
    return [*lines, ""]
