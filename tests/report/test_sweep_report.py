"""lq report on real bags from a small real sweep: figures are non-trivial, pages link to existing bags."""

from __future__ import annotations

import json
import os
import re
import shutil
from pathlib import Path

import matplotlib.image as mpimg
import matplotlib.pyplot as plt
import numpy as np
import pytest

from lq_ros.report import figures as fg
from lq_ros.report import sweep_report as rp
from lq_ros.report.escape import md_text
from lq_ros.run import sweep as sw

pytestmark = [pytest.mark.slow, pytest.mark.sim]


@pytest.fixture(scope="module")
def sweep_dir(tmp_path_factory) -> Path:
    """scripted x {sync, async} x {0, 0.1} s, two init states: 8 real in-process episodes that succeed
    (trajectory and energy figures are over successful episodes)."""
    out = tmp_path_factory.mktemp("sweep")
    spec = sw.expand_spec(
        {
            "name": "report-test",
            "transport": "inprocess",
            "tasks": [0],
            "inits": [0, 1],
            "policies": ["scripted"],
            "latencies_s": [0.0, 0.1],
            "modes": ["sync", "async"],
        }  # fmt: skip
    )
    summary = sw.run_sweep(spec, out, workers=2)
    assert summary.counts == {"success": 8}
    return out


@pytest.fixture(scope="module")
def report(sweep_dir):
    result = rp.build_report(sweep_dir, n_boot=300, keep_figures=True)
    yield result
    for fig in result.figures.values():
        plt.close(fig)


def _lines_with_data(ax) -> list:
    return [line for line in ax.get_lines() if len(line.get_xdata()) and np.isfinite(line.get_ydata()).any()]


def _hollow_means(ax) -> list[tuple[float, float]]:
    """The means drawn hollow and unjoined (fewer than 5 values: lq_ros/report/plot_rules.py)."""
    return [tuple(xy) for c in ax.collections if len(c.get_offsets()) and not len(c.get_facecolors())
            and c.get_sizes()[0] == 40 for xy in c.get_offsets()]  # fmt: skip


def test_figures_have_the_papers_panels_and_series(report):
    figs = report.figures
    fig4 = figs["fig4_success"].axes
    assert [ax.get_title() for ax in fig4] == ["sync execution", "async execution"]
    for ax in fig4:
        (line,) = _lines_with_data(ax)  # one policy
        assert list(line.get_xdata()) == [0.0, 0.1] and np.allclose(line.get_ydata(), 100.0)
        assert ax.collections, "no CI band"
        assert [t.get_text() for t in ax.get_xticklabels()] == ["0\nN=0", "0.1\nN=2"]  # applied latency and N
    fig5 = figs["fig5_trajectory"].axes
    # scripted x {sync, async} x {0, 0.1 s}: two values a cell, so every mean is a hollow point and none is joined
    assert len(fig5) == 4 and [len(_hollow_means(ax)) for ax in fig5] == [4, 4, 4, 4]
    assert not any(_lines_with_data(ax) for ax in fig5)
    assert "successful episodes; traj 20 Hz, energy substep" in figs["fig5_trajectory"].texts[0].get_text()
    assert "jerk" in fig5[0].get_ylabel() and "EE-Osc, paper A.3" in fig5[2].get_ylabel()
    assert "EE-Osc detrended" in fig5[3].get_ylabel() and fig5[2].get_ylim() == fig5[3].get_ylim()  # one scale
    # Two episodes per cell: no band, the values as dots and n beside each point.
    assert "n=2" in [t.get_text() for t in fig5[0].texts]
    fig6 = figs["fig6_energy_decomposition"].axes
    # A row per series (2), each (a) and (b): 2 latencies' bars per stacked part, 3 parts in (a), 2 in (b)
    assert [len(ax.patches) for ax in fig6] == [2 * 3, 2 * 2, 2 * 3, 2 * 2]
    assert all(p.get_height() > 0 for p in fig6[0].patches)
    fig7 = figs["fig7_energy"].axes
    assert len(fig7) == 2 and [len(_hollow_means(ax)) for ax in fig7] == [4, 4]
    totals = np.array([y for _, y in _hollow_means(fig7[1])])
    assert np.all(totals > 85.0 * 50 * 0.05)  # at least the 85 W overhead over 50 ticks


@pytest.mark.parametrize("name", list(fg.FIGURES))
def test_png_is_not_blank(report, name):
    image = mpimg.imread(report.files[f"{name}.png"])[..., :3]
    assert image.shape[0] > 300 and image.shape[1] > 500
    not_white = (image < 0.95).any(axis=2).mean()
    assert 0.02 < not_white < 0.9, not_white  # drawn on, but not a solid block
    assert len(np.unique((image * 255).astype(np.uint8).reshape(-1, 3), axis=0)) > 20  # several colours


def test_pages_tables_provenance_and_links(report, sweep_dir):
    html = report.files["report.html"].read_text()
    md = report.files["report.md"].read_text()
    for name in fg.FIGURES:
        assert f"({name}.png)" in md
    assert html.count("<img src='data:image/png;base64,") >= len(fg.FIGURES)  # the page carries its figures
    assert md.startswith("# LIBERO-LQ sweep report\n\n## Summary\n") and md.index("## Methods") > md.index("Fig. 4")
    links = re.findall(r"href='([^']+)'", html)
    assert len(links) == 8
    for link in links:
        assert (report.out_dir / link / "metadata.yaml").exists(), link
    assert re.findall(r"\[bag\]\(([^)]+)\)", md) == []  # per-episode rows: report.html and episodes.csv
    for key in ("mujoco", "git_commit", "seeds", "init states", "transports"):
        assert key in html and key in md
    assert "2.3.7" in html  # the MuJoCo version the episodes ran on
    assert "| episodes of the spec not finished | 0 |" in md
    for table in ("episodes.csv", "episodes.parquet", "aggregates.csv", "aggregates.parquet", "aggregates_pooled.csv",
                  "paired_vs_zero_latency.csv"):  # fmt: skip
        assert report.files[table].stat().st_size > 100
    assert report.skipped == []  # every real record passes its checks
    assert len(report.pooled) == 4 and set(report.pooled["n"]) == {2}
    # Every 0.1 s cell against its 0 s cell over the two init states (both succeed at both latencies).
    assert len(report.paired) == 2 and set(report.paired["n_pairs"]) == {2}
    assert "## Latency effects (paired against 0 s)" in md and "over the 2 pairs that succeed in both" in md
    assert "Async best case" in md and "no request slack" in html


def test_report_of_a_plain_bag_folder(sweep_dir, tmp_path):
    """Without a sweep store, the bags themselves are scored."""
    result = rp.build_report(sweep_dir / "bags", tmp_path / "r", n_boot=100)
    assert len(result.episodes) == 8 and result.files["report.html"].exists()


def test_empty_folder_is_a_clear_error(tmp_path):
    with pytest.raises(FileNotFoundError, match="no scored episodes"):
        rp.build_report(tmp_path)


def test_hostile_results_are_skipped_by_name_and_the_rest_reported(sweep_dir, tmp_path, no_hang):
    """FIFOs, a link to /dev/zero and records that contradict themselves: the report is written for the rest."""
    folder = tmp_path / "sweep"
    shutil.copytree(sweep_dir, folder, symlinks=True, ignore=shutil.ignore_patterns("report"))
    (folder / "manifest.json").unlink()
    os.mkfifo(folder / "manifest.json")  # would block a plain open() forever
    os.mkfifo(folder / "results" / "fifo.json")
    (folder / "results" / "zero.json").symlink_to("/dev/zero")
    paths = sorted((folder / "results").glob("*.json"))
    paths = [p for p in paths if p.name not in ("fifo.json", "zero.json")]
    records = {p: json.loads(p.read_text()) for p in paths}
    damage = {
        "status error but the row's status is success": lambda r: r.update(status="error"),
        "row: completion_time_s -2.5 is negative": lambda r: r["row"].update(completion_time_s=-2.5),
        "row: task '0' is not a whole number >= 0": lambda r: r["row"].update(task="0"),
        "row: the row is a list, not an object of fields": lambda r: r.update(row=[r["row"]]),
        "attempts is a str, not a list": lambda r: r.update(attempts="none"),
    }
    for path, change in zip(paths, damage.values(), strict=False):
        change(records[path])
        path.write_text(json.dumps(records[path]))
    result = rp.build_report(folder, n_boot=50)
    assert len(result.episodes) == len(paths) - len(damage)
    expected = [f"results file {path}: {why}" for path, why in zip(paths, damage, strict=False)]
    expected += [
        f"manifest {folder / 'manifest.json'}: not a regular file; every finished episode is used",
        f"results file {folder / 'results' / 'fifo.json'}: not a regular file",
        f"results file {folder / 'results' / 'zero.json'}: a link, not a regular file",
    ]
    assert sorted(result.skipped) == sorted(expected)
    md = result.files["report.md"].read_text()
    html = result.files["report.html"].read_text()
    assert "## Skipped files" in md and "<h2>Skipped files</h2>" in html
    for line in expected:
        assert md_text(line) in md
    assert "zero.json: a link, not a regular file" in html


def test_damaged_foreign_and_same_named_bags_in_a_bag_folder(sweep_dir, tmp_path, no_hang):
    """A bag without metadata.yaml and a truncated one are skipped by name; two bags of one folder name (under
    a/ and b/) get a figure each."""
    bags = sorted(p for p in (sweep_dir / "bags").iterdir() if (p / "metadata.yaml").exists())
    folder = tmp_path / "bags"
    for where, bag in [("a", bags[0]), ("b", bags[0]), ("a", bags[1]), ("c", bags[2]), ("c", bags[3])]:
        shutil.copytree(bag, folder / where / bag.name)
    (folder / "c" / bags[2].name / "metadata.yaml").unlink()  # a recorder that died: a plain MCAP
    damaged = folder / "c" / bags[3].name
    (damaged / "metadata.yaml").unlink()
    for mcap in damaged.glob("*.mcap"):
        mcap.write_bytes(mcap.read_bytes()[:300])
    result = rp.build_report(folder, n_boot=50)
    assert len(result.episodes) == 3 and len(result.skipped) == 2
    assert [line.split(":")[0] for line in sorted(result.skipped)] == [f"bag c/{bags[2].name}", f"bag c/{bags[3].name}"]
    assert all("no run configuration" in line for line in result.skipped)
    plots = list(result.episodes["plot"])
    assert len(set(plots)) == 3 and all((result.out_dir / p).is_file() for p in plots)
    page = result.files["report.html"].read_text()  # (report.md has no per-episode rows)
    assert len(set(re.findall(r"href=[\"']([^\"']+[.]png)[\"']>plot<", page))) == 3
    # lq report names each skipped bag on the console, one line each, and writes the report for the rest.
    from typer.testing import CliRunner

    from lq_ros.cli import app

    run = CliRunner().invoke(app, ["report", str(folder), "--out", str(tmp_path / "again")])
    assert run.exit_code == 0, run.output
    lines = [" ".join(line.split()) for line in run.output.splitlines() if line.startswith("skipped:")]
    assert [line.split(":")[1].strip() for line in lines] == [f"bag c/{bags[2].name}", f"bag c/{bags[3].name}"]
    assert "3 episodes ->" in run.output and "Traceback" not in run.output
