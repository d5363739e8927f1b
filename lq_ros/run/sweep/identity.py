"""The identity of the code that made a result, so a resumed sweep never mixes results of different code.

Each finished record carries ``code`` (see :func:`code_identity`): the policy's class, a hash of its module's
source (a package: every ``.py`` file under it), the effective policy arguments (the constructor's defaults
with the given ones over them, secrets redacted), the package version and the git commit of the checkout.
A resume compares the records already in the folder with the code about to run; an episode made by other
code is not skipped: the sweep refuses in one line naming what changed (``--overwrite`` reruns everything).
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
FIELDS = ("policy_class", "policy_source_sha256", "policy_args", "lq_ros", "git_commit")


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


def source_hash(cls: type) -> str:
    """sha256 (16 hex digits) of the policy's source as it is on disk now ('unknown' without a source file)."""
    files = _source_files(cls)
    if not files:
        return "unknown"
    digest = hashlib.sha256()
    for path in files:
        digest.update(path.name.encode() + b"\0")
        try:
            digest.update(path.read_bytes())
        except OSError:
            return "unknown"
    return digest.hexdigest()[:16]


#: module name -> the source hash of a user's policy module when this process last (re)imported it.
_LOADED: dict[str, str] = {}


def _current(cls: type) -> type:
    """``cls`` as its source on disk defines it now: a user's module edited since this process imported it is
    imported again (a long-lived process, a notebook, would otherwise record the old defaults). The project's
    own modules are not reloaded (their edits show in the git commit)."""
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


def code_identity(policy: str, args: dict, commit: str | None = None) -> dict:
    """The identity of the code an episode of ``policy`` with ``args`` runs (the policy's module is imported)."""
    import lq_ros
    from lq_ros.policies import policy_class

    cls = _current(policy_class(policy))
    return {
        "policy_class": f"{cls.__module__}:{cls.__qualname__}",
        "policy_source_sha256": source_hash(cls),
        "policy_args": effective_args(cls, args),
        "lq_ros": lq_ros.__version__,
        "git_commit": git_commit() if commit is None else commit,
    }


def identities(configs: list[RunConfig] | tuple[RunConfig, ...]) -> dict[str, dict]:
    """RunConfig.key() -> the code identity of that episode (each distinct policy resolved once)."""
    commit = git_commit()
    by_policy: dict[tuple, dict] = {}
    out = {}
    for cfg in configs:
        ident = (cfg.policy, json.dumps(cfg.policy_args, sort_keys=True, default=repr))
        if ident not in by_policy:
            by_policy[ident] = code_identity(cfg.policy, cfg.policy_args, commit)
        out[cfg.key()] = by_policy[ident]
    return out


def _short(value: object) -> str:
    text = value if isinstance(value, str) else json.dumps(value)
    return text[:40] + "..." if len(text) > 43 else text


def changes(old: dict | None, new: dict) -> list[str]:
    """What differs between the identity a record holds and the code about to run, in words ([] if none)."""
    if not isinstance(old, dict):
        return ["the results record no code identity (made by an older lq)"]
    out = []
    for field in FIELDS:
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
        else:
            out.append(f"{field} {_short(before)} -> {_short(after)}")
    return out
