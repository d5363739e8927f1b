"""Every relative link in README.md and docs/**/*.md resolves, anchors included.

A link resolves when its target exists in the repository and is not git-ignored (GitHub shows only committed
files). A `#anchor` must match a heading of the target page, slugged as GitHub slugs it.
"""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

# The demo report is `lq report`'s output copied into docs/; its per-episode links point into the sweep folder,
# which stays uncommitted (docs/demo_report/README.md says so). Only those link prefixes are exempt.
UNCOMMITTED_TARGETS = {"docs/demo_report/report.md": ("episodes/", "../bags/")}

_FENCE = re.compile(r"^\s*(```|~~~)")
_INLINE_CODE = re.compile(r"(`+)(?:(?!\1).)+?\1")
_INLINE_LINK = re.compile(r"\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
_REF_DEF = re.compile(r"^\s{0,3}\[[^\]]+\]:\s*<?(\S+?)>?(?:\s|$)")
_HTML_ATTR = re.compile(r"<(?:a|img)\b[^>]*?\b(?:href|src)\s*=\s*\"([^\"]+)\"", re.IGNORECASE)
_HTML_ID = re.compile(r"<a\b[^>]*?\b(?:id|name)\s*=\s*\"([^\"]+)\"", re.IGNORECASE)
_HEADING = re.compile(r"^\s{0,3}(#{1,6})\s+(.*?)\s*#*\s*$")


def doc_files() -> list[Path]:
    return [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]


def prose_lines(text: str) -> list[str]:
    """The lines outside fenced code blocks."""
    out, fenced = [], False
    for line in text.splitlines():
        if _FENCE.match(line):
            fenced = not fenced
            continue
        if not fenced:
            out.append(line)
    return out


def github_slug(heading: str) -> str:
    """GitHub's anchor for a heading's text: markup dropped, lower case, punctuation removed, spaces to '-'."""
    text = re.sub(r"!?\[([^\]]*)\]\([^)]*\)", r"\1", heading)  # a link renders as its text
    text = re.sub(r"<[^>]+>", "", text)  # inline HTML tags render as nothing
    text = re.sub(r"[^\w\- ]", "", text.lower())
    return text.replace(" ", "-")


def anchors(path: Path) -> set[str]:
    """Every anchor a page offers: its headings' slugs (repeats get -1, -2, ...) and explicit HTML ids."""
    seen: dict[str, int] = {}
    out: set[str] = set()
    for line in prose_lines(path.read_text(encoding="utf-8")):
        out.update(_HTML_ID.findall(line))
        m = _HEADING.match(line)
        if not m:
            continue
        slug = github_slug(m.group(2))
        n = seen.get(slug, 0)
        seen[slug] = n + 1
        out.add(slug if n == 0 else f"{slug}-{n}")
    return out


def links(path: Path) -> list[tuple[int, str]]:
    """(line number, target) of every link outside code: inline, reference definitions, HTML href/src."""
    found = []
    fenced = False
    for no, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
        if _FENCE.match(line):
            fenced = not fenced
            continue
        if fenced:
            continue
        line = _INLINE_CODE.sub("", line)
        for rx in (_INLINE_LINK, _REF_DEF, _HTML_ATTR):
            found.extend((no, t) for t in rx.findall(line))
    return found


def _git_ignored(paths: list[Path]) -> set[Path]:
    if not paths or shutil.which("git") is None or not (ROOT / ".git").exists():
        return set()
    proc = subprocess.run(
        ["git", "check-ignore", "--stdin"],
        input="\n".join(str(p) for p in paths),
        capture_output=True,
        text=True,
        cwd=ROOT,
        check=False,
    )
    return {Path(line) for line in proc.stdout.splitlines()}


def broken_links(path: Path) -> list[str]:
    """One line per link of `path` that does not resolve."""
    rel = path.relative_to(ROOT).as_posix()
    exempt = UNCOMMITTED_TARGETS.get(rel, ())
    problems: list[str] = []
    checked: list[tuple[int, str, Path, str]] = []
    for no, target in links(path):
        if re.match(r"^[a-zA-Z][a-zA-Z0-9+.-]*:", target) or target.startswith("//"):
            continue  # a URL (http:, mailto:, ...), not a relative link
        if exempt and target.startswith(exempt):
            continue
        file_part, _, anchor = target.partition("#")
        dest = (path.parent / file_part).resolve() if file_part else path
        if ROOT not in dest.parents and dest != ROOT:
            problems.append(f"{rel}:{no}: {target} points outside the repository")
        elif not dest.exists():
            problems.append(f"{rel}:{no}: {target} does not exist")
        else:
            checked.append((no, target, dest, anchor))
    ignored = _git_ignored([d for _, _, d, _ in checked])
    for no, target, dest, anchor in checked:
        if dest in ignored:
            problems.append(f"{rel}:{no}: {target} is git-ignored, so not on GitHub")
        elif anchor and dest.suffix == ".md" and anchor not in anchors(dest):
            problems.append(f"{rel}:{no}: {target}: no heading with anchor #{anchor} in {dest.relative_to(ROOT)}")
    return problems


@pytest.mark.parametrize("path", doc_files(), ids=lambda p: p.relative_to(ROOT).as_posix())
def test_relative_links_resolve(path: Path) -> None:
    problems = broken_links(path)
    assert not problems, "broken links:\n" + "\n".join(problems)


@pytest.mark.parametrize(
    ("heading", "slug"),
    [
        ("Request slack (`--request-slack K`)", "request-slack---request-slack-k"),
        ("Delay-aware variants (`--policy-arg variant=delay`)", "delay-aware-variants---policy-arg-variantdelay"),
        ("Policies (`lq_ros.policies`)", "policies-lq_rospolicies"),
        ("Managed nodes ([docs/design/lifecycle.md](docs/design/lifecycle.md))", "managed-nodes-docsdesignlifecyclemd"),
        ("Latency Δt_sim: 0.1 s", "latency-δt_sim-01-s"),
    ],
)
def test_github_slug(heading: str, slug: str) -> None:
    assert github_slug(heading) == slug


def test_checker_catches_broken_links(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    tmp_path = tmp_path.resolve()
    monkeypatch.setattr(sys.modules[__name__], "ROOT", tmp_path)
    (tmp_path / "a.md").write_text("# Top\n\n## Same\n\n## Same\n", encoding="utf-8")
    page = tmp_path / "b.md"
    page.write_text(
        "[ok](a.md#same-1) [gone](missing.md) [bad anchor](a.md#nope) [self](#here)\n"
        "```\n[in code](missing2.md)\n```\n`[inline](missing3.md)` [web](https://example.org/x.md)\n",
        encoding="utf-8",
    )
    problems = broken_links(page)
    assert len(problems) == 3, problems
    assert any("missing.md does not exist" in p for p in problems)
    assert any("#nope" in p for p in problems)
    assert any("#here" in p for p in problems)
