"""Text read from bags and results files (policy names, suites, task text, failure reasons, bag folder names) as
literal text in report.md and report.html.

Bags may come from anyone (docs/design/trust.md): a policy named ``<script>`` or ``a | b`` is data, never markup.
report.md gets :func:`md_text` for every such string (a ``|`` would end a table cell, ``<script>`` is raw HTML to
most renderers, ``[x](javascript:...)`` a link, a newline a new block); report.html gets ``html.escape``, and the
report's own sentences, written in markdown with their names escaped, reach it through :func:`md_to_html`. The
CSV files keep the text as it was read.
"""

from __future__ import annotations

import html
import re
import unicodedata
from urllib.parse import quote

import pandas as pd

#: Characters that are markup in (GitHub-flavoured) markdown inside a line: each gets a backslash, except an
#: underscore between two letters or digits (``libero_spatial``), which CommonMark never reads as emphasis.
MD_SPECIAL = "\\|*_`<>[]"
_MD_SPECIAL_RE = re.compile(r"([\\|*`<>\[\]]|(?<![^\W_])_|_(?![^\W_]))")
#: ``**bold**``: the only markup of the report's sentences (besides the escapes of :func:`md_text`).
_BOLD_RE = re.compile(r"[*][*](.+?)[*][*]")
_ESCAPED_RE = re.compile(r"\\([" + re.escape(MD_SPECIAL) + "])")


def one_line(value: object) -> str:
    """``value`` as text on one line: runs of whitespace (newlines, tabs, Unicode line separators) become one space,
    other control characters U+FFFD."""
    text = " ".join(str(value).split())
    return "".join("\ufffd" if unicodedata.category(c) == "Cc" else c for c in text)


def md_text(value: object) -> str:
    """``value`` as literal markdown on one line: every character of MD_SPECIAL gets a backslash (an underscore
    inside a word excepted)."""
    return _MD_SPECIAL_RE.sub(r"\\\1", one_line(value))


def md_table(frame: pd.DataFrame) -> str:
    """``frame`` as a markdown table with every text cell and header through :func:`md_text` (numbers as they are)."""
    shown = frame.map(lambda v: md_text(v) if isinstance(v, str) else v)
    shown.columns = [md_text(c) for c in frame.columns]
    return shown.to_markdown(index=False)


def md_link_target(path: str) -> str:
    """A relative path as a markdown link target: percent-encoded (no space, parenthesis or scheme can end or turn
    the link), ``./`` in front so that a name with a colon is never read as a URL scheme."""
    return "./" + quote(str(path).lstrip("/"), safe="/=,+@")


def md_to_html(markdown: str) -> str:
    """A report sentence (markdown whose only markup is ``**bold**`` and the backslash escapes of :func:`md_text`)
    as escaped HTML: bold as ``<b>``, an escaped character as itself."""
    kept: list[str] = []
    markdown = markdown.replace("\x00", "\ufffd")  # the placeholder's delimiter

    def hold(match: re.Match) -> str:  # an escaped character takes no part in the bold markup
        kept.append(match.group(1))
        return f"\x00{len(kept) - 1}\x00"

    text = html.escape(_ESCAPED_RE.sub(hold, markdown))
    text = _BOLD_RE.sub(r"<b>\1</b>", text)
    return re.sub("\x00([0-9]+)\x00", lambda m: html.escape(kept[int(m.group(1))]), text)
