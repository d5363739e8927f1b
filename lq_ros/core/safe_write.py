"""Files the stack writes into folders it did not make this run (bag, report and sweep folders, ``--out``).

Such a folder may come from anyone (a bag folder someone sent you) or be shared, so a name in it may be a link
planted to make the stack overwrite a file elsewhere. Every write here goes to a fresh temporary name opened
with ``O_CREAT | O_EXCL | O_NOFOLLOW`` (a random suffix: never a name someone could have planted), is flushed to
disk, then renamed onto the target (``rename`` replaces a link, never follows it). A target that is already a
link is refused in one line. CSV text cells are escaped the OWASP way (:func:`csv_cell`).
"""

from __future__ import annotations

import contextlib
import os
import re
import secrets
import stat
from collections.abc import Iterator
from pathlib import Path
from typing import IO, Any


class WriteRefused(OSError):
    """A file or folder the stack will not write: one line naming it and why."""


def refuse_link(path: Path) -> None:
    """WriteRefused if ``path`` is a link or a folder. A rename would replace the link, but a link there was
    planted by someone: say so rather than remove it silently. Every write checks; a caller may check earlier,
    before long work."""
    try:
        info = os.lstat(path)
    except FileNotFoundError:
        return
    if stat.S_ISLNK(info.st_mode):
        raise WriteRefused(f"{path}: a symbolic link where a file is written; not followed (remove it, or choose "
                           "another output folder)")  # fmt: skip
    if stat.S_ISDIR(info.st_mode):
        raise WriteRefused(f"{path}: a folder where a file is written (remove it, or choose another output folder)")


@contextlib.contextmanager
def replacing(path: Path | str, binary: bool = False, mode: int = 0o644) -> Iterator[IO[Any]]:
    """A file object whose content replaces ``path`` when the block ends without an exception (whole or not at
    all); written under a fresh temporary name in the same folder, never through a link. ``mode`` as for
    ``open``: the umask narrows it."""
    path = Path(path)
    refuse_link(path)
    tmp = path.with_name(f".{path.name}.{secrets.token_hex(8)}.tmp")
    try:
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW | os.O_CLOEXEC, mode)
    except OSError as exc:
        raise WriteRefused(f"{path}: cannot write ({exc.strerror})") from None
    try:
        with os.fdopen(fd, "wb" if binary else "w", encoding=None if binary else "utf-8", newline=None) as f:
            yield f
            f.flush()
            os.fsync(f.fileno())
        refuse_link(path)  # planted while we wrote: still not removed silently
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise
    _fsync_dir(path.parent)


def _fsync_dir(path: Path) -> None:
    with contextlib.suppress(OSError):  # some file systems cannot fsync a folder: the rename stands anyway
        fd = os.open(path, os.O_RDONLY | os.O_DIRECTORY | os.O_CLOEXEC)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


def reserve_temporary(path: Path | str) -> Path:
    """A new, empty file next to ``path`` under a fresh random name (``O_EXCL | O_NOFOLLOW``), for a writer that
    opens files by name (ffmpeg); :func:`commit` renames it onto ``path`` when complete."""
    path = Path(path)
    refuse_link(path)
    tmp = path.with_name(f".{path.name}.{secrets.token_hex(8)}.tmp")
    try:
        os.close(os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW | os.O_CLOEXEC, 0o644))
    except OSError as exc:
        raise WriteRefused(f"{path}: cannot write ({exc.strerror})") from None
    return tmp


def commit(tmp: Path | str, path: Path | str) -> Path:
    """Rename the finished temporary file ``tmp`` onto ``path`` (refused if ``path`` is a link or a folder)."""
    path = Path(path)
    refuse_link(path)
    os.replace(tmp, path)
    _fsync_dir(path.parent)
    return path


def write_bytes(path: Path | str, data: bytes, mode: int = 0o644) -> Path:
    """``data`` as the file ``path``, whole or not at all, never through a link; returns ``path``."""
    with replacing(path, binary=True, mode=mode) as f:
        f.write(data)
    return Path(path)


def write_text(path: Path | str, text: str, mode: int = 0o644) -> Path:
    """``text`` (UTF-8) as the file ``path``, whole or not at all, never through a link; returns ``path``."""
    return write_bytes(path, text.encode("utf-8"), mode)


def save_figure(fig, path: Path | str, **kwargs) -> Path:
    """A matplotlib figure saved to ``path`` (format from its suffix) without following a link."""
    path = Path(path)
    kwargs.setdefault("format", path.suffix.lstrip(".") or "png")
    with replacing(path, binary=True) as f:
        fig.savefig(f, **kwargs)
    return path


# -- CSV cells --------------------------------------------------------------------------------------------------

#: First characters that make a spreadsheet read a cell as a formula (OWASP, "CSV Injection"): = + - @, and tab
#: or carriage return (which some spreadsheets strip before looking again).
FORMULA_STARTS = ("=", "+", "-", "@", "\t", "\r")
_NUMBER = re.compile(r"[+-]?(\d+\.?\d*|\.\d+)([eE][+-]?\d+)?")


def csv_cell(value):
    """A text cell a spreadsheet will show as text: one that starts like a formula gets a leading ``'`` (OWASP's
    rule). Numbers, and text that is a plain number (``-0.2``), are unchanged; so is everything not text."""
    if isinstance(value, str) and value.startswith(FORMULA_STARTS) and not _NUMBER.fullmatch(value):
        return "'" + value
    return value


def csv_safe(frame):
    """A copy of the pandas DataFrame ``frame`` whose text cells pass :func:`csv_cell` (numeric columns as they
    are)."""
    frame = frame.copy()
    for column in frame.columns:
        if frame[column].dtype.kind == "O" or str(frame[column].dtype).startswith("string"):
            frame[column] = frame[column].map(csv_cell, na_action="ignore")
    return frame


def write_csv(frame, path: Path | str, **kwargs) -> Path:
    """The pandas DataFrame ``frame`` as a CSV file, text cells escaped (:func:`csv_cell`), never through a link;
    ``kwargs`` go to ``DataFrame.to_csv`` (index defaults to False)."""
    kwargs.setdefault("index", False)
    with replacing(path) as f:
        csv_safe(frame).to_csv(f, **kwargs)
    return Path(path)


# -- output folders ---------------------------------------------------------------------------------------------


def output_folder(path: Path | str, what: str = "--out", follow: bool = True) -> Path:
    """``path`` as a folder this user may write results into, made if missing; WriteRefused (one line) if it is a
    regular file, a dangling link, or a folder of another user. A link to one of this user's folders is used when
    ``follow`` (a folder the user named); not otherwise (a folder the stack names inside one it did not make)."""
    path = Path(path)
    try:
        info = os.lstat(path)
    except FileNotFoundError:
        info = None
    except OSError as exc:
        raise WriteRefused(f"{what} {path}: cannot use it ({exc.strerror})") from None
    if info is not None and stat.S_ISLNK(info.st_mode) and not path.exists():
        raise WriteRefused(f"{what} {path}: a link to nothing (dangling); give a folder")
    if info is not None and stat.S_ISLNK(info.st_mode) and not follow:
        raise WriteRefused(f"{what} {path}: a symbolic link; not followed (remove it, or choose another folder)")
    if info is None:
        try:
            path.mkdir(parents=True, exist_ok=True)
        except FileExistsError:
            raise WriteRefused(f"{what} {path}: a part of it is a file, not a folder") from None
        except OSError as exc:
            raise WriteRefused(f"{what} {path}: cannot make the folder ({exc.strerror})") from None
    try:
        target = os.stat(path)
    except OSError as exc:
        raise WriteRefused(f"{what} {path}: cannot use it ({exc.strerror})") from None
    if not stat.S_ISDIR(target.st_mode):
        raise WriteRefused(f"{what} {path}: a file, not a folder; give a folder")
    if target.st_uid != os.getuid():
        raise WriteRefused(f"{what} {path}: a folder of user id {target.st_uid}, not this user's (id {os.getuid()}); "
                           "give a folder of your own")  # fmt: skip
    return path
