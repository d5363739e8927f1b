"""The identity of the code that made a result, so a resumed sweep never mixes results of different code.

Each finished record carries ``code`` (see :func:`code_identity`): the policy's class, a hash of its module's
source (a package: every ``.py`` file under it), the effective policy arguments (the constructor's defaults
with the given ones over them, secrets redacted), the package version, a hash of the project's own source (every
``.py`` file of lq_ros and of its node programs) and, as provenance only, the git commit of the checkout.
A resume compares the records already in the folder with the code about to run (``COMPARED``: the code, not the
commit, so a commit or an uncommitted edit that changes no source, e.g. of the docs, resumes); an episode made by
other code is not skipped: the sweep refuses in one line naming what changed (``--overwrite`` reruns everything).
Refusing, not rerunning: a stray edit must not silently throw away hours of finished episodes, and a folder
must never hold rows of two versions of a policy.
"""

from __future__ import annotations

import hashlib
import inspect
import json
import re
import sys
from pathlib import Path

from lq_ros.core.redact import redact_args
from lq_ros.core.run_config import RunConfig, git_commit

#: The record field that holds the identity (results/<key>.json, episodes.jsonl).
CODE_FIELD = "code"
#: The identity's fields, in the order a change is named.
FIELDS = ("policy_class", "policy_source_sha256", "policy_args", "lq_ros", "lq_ros_source_sha256", "git_commit")
#: The fields a resume compares: what the code is. The commit is provenance: a docs-only commit changes it, and
#: a checkout's "+dirty" follows any tracked edit, so comparing it would refuse results of identical code.
COMPARED = FIELDS[:-1]
#: Compared instead of the project's source hash when a record predates it (the rule it was made under).
LEGACY_FIELD = "git_commit"


def _source_files(cls: type) -> list[Path]:
    """The files whose text is the policy: its module's file, or every .py file of its package."""
    module = sys.modules.get(cls.__module__)
    file = getattr(module, "__file__", None) or inspect.getsourcefile(cls)
    if not file:
        return []
    path = Path(file)
    if path.name == "__init__.py":
        return sorted(path.parent.rglob("*.py"))
    return [path]


def _files_hash(files: list[Path], root: Path | None = None) -> str:
    """sha256 (16 hex digits) of ``files``' names (relative to ``root`` if given) and bytes ('unknown' if none or
    one cannot be read)."""
    if not files:
        return "unknown"
    digest = hashlib.sha256()
    for path in files:
        name = path.relative_to(root).as_posix() if root is not None else path.name
        digest.update(name.encode() + b"\0")
        try:
            digest.update(path.read_bytes())
        except OSError:
            return "unknown"
    return digest.hexdigest()[:16]


def source_hash(cls: type) -> str:
    """sha256 (16 hex digits) of the policy's source as it is on disk now ('unknown' without a source file)."""
    return _files_hash(_source_files(cls))


def _node_programs() -> Path | None:
    """The folder of the node programs: nodes/ beside the package in a checkout, lq_ros_nodes when installed."""
    import importlib.util

    import lq_ros

    checkout = Path(lq_ros.__file__).resolve().parent.parent / "nodes"
    if checkout.is_dir():
        return checkout
    spec = importlib.util.find_spec("lq_ros_nodes")
    return Path(spec.origin).parent if spec is not None and spec.origin else None


def project_source_hash() -> str:
    """sha256 (16 hex digits) of every .py file of the lq_ros package and of its node programs, as on disk now:
    the project's code, which the git commit is not (a docs edit changes the commit, not the code)."""
    import lq_ros

    package = Path(lq_ros.__file__).resolve().parent
    roots = [package] + [p for p in (_node_programs(),) if p is not None]
    files = sorted(f for root in roots for f in root.rglob("*.py") if "__pycache__" not in f.parts)
    return _files_hash(files, package.parent)


#: module name -> the source hash of a user's policy module when this process last (re)imported it.
_LOADED: dict[str, str] = {}


def _current(cls: type) -> type:
    """``cls`` as its source on disk defines it now: a user's module edited since this process imported it is
    imported again (a long-lived process, a notebook, would otherwise record the old defaults). The project's
    own modules are not reloaded (their edits show in the project's source hash)."""
    import importlib

    name = cls.__module__
    now = source_hash(cls)
    if name.split(".")[0] == "lq_ros" or name not in sys.modules:
        return cls
    if _LOADED.setdefault(name, now) != now:
        importlib.invalidate_caches()
        module = importlib.reload(sys.modules[name])
        _LOADED[name] = now
        return getattr(module, cls.__qualname__, cls)
    return cls


def _plain(value: object) -> object:
    """A JSON value as a record holds it (a default that is no JSON value: its repr, without the memory address
    an object's repr may carry, which differs in every process)."""
    return json.loads(json.dumps(value, default=lambda v: re.sub(r" at 0x[0-9a-fA-F]+", "", repr(v))))


def effective_args(cls: type, args: dict) -> dict:
    """The constructor's defaults with ``args`` over them, secrets redacted: what the policy was built with."""
    from lq_ros.run.validation import policy_arguments

    params, _, _ = policy_arguments(cls)
    defaults = {n: p.default for n, p in params.items() if p.default is not p.empty}
    return _plain(redact_args(defaults | dict(args)))


def code_identity(policy: str, args: dict, commit: str | None = None, project: str | None = None) -> dict:
    """The identity of the code an episode of ``policy`` with ``args`` runs (the policy's module is imported);
    ``commit`` and ``project`` (its source hash) when the caller has them already."""
    import lq_ros
    from lq_ros.policies import policy_class

    cls = _current(policy_class(policy))
    return {
        "policy_class": f"{cls.__module__}:{cls.__qualname__}",
        "policy_source_sha256": source_hash(cls),
        "policy_args": effective_args(cls, args),
        "lq_ros": lq_ros.__version__,
        "lq_ros_source_sha256": project_source_hash() if project is None else project,
        "git_commit": git_commit() if commit is None else commit,
    }


def identities(configs: list[RunConfig] | tuple[RunConfig, ...]) -> dict[str, dict]:
    """RunConfig.key() -> the code identity of that episode (each distinct policy resolved once)."""
    commit, project = git_commit(), project_source_hash()
    by_policy: dict[tuple, dict] = {}
    out = {}
    for cfg in configs:
        ident = (cfg.policy, json.dumps(cfg.policy_args, sort_keys=True, default=repr))
        if ident not in by_policy:
            by_policy[ident] = code_identity(cfg.policy, cfg.policy_args, commit, project)
        out[cfg.key()] = by_policy[ident]
    return out


def _short(value: object) -> str:
    text = value if isinstance(value, str) else json.dumps(value)
    return text[:40] + "..." if len(text) > 43 else text


def changes(old: dict | None, new: dict) -> list[str]:
    """What differs between the code identity a record holds and the code about to run, in words ([] if none):
    the ``COMPARED`` fields (a record without the project's source hash: its git commit instead)."""
    if not isinstance(old, dict):
        return ["the results record no code identity (made by an older lq)"]
    out = []
    legacy = "lq_ros_source_sha256" not in old
    for field in COMPARED if not legacy else (*COMPARED[:-1], LEGACY_FIELD):
        before, after = old.get(field), new.get(field)
        if before == after:
            continue
        if field == "policy_args" and isinstance(before, dict) and isinstance(after, dict):
            for name in sorted(set(before) | set(after)):
                if before.get(name, "(unset)") != after.get(name, "(unset)"):
                    out.append(
                        f"policy_args.{name} {_short(before.get(name, '(unset)'))} -> "
                        f"{_short(after.get(name, '(unset)'))}"
                    )
        elif field == "policy_source_sha256":
            out.append(f"the source of {new.get('policy_class', 'the policy')} changed")
        elif field == "lq_ros_source_sha256":
            out.append("the source of lq_ros changed")
        else:
            out.append(f"{field} {_short(before)} -> {_short(after)}")
    return out
