"""Secrets out of results: the one function every place that writes or shows policy arguments calls.

Policy arguments (``--policy-arg``, a sweep spec's ``policy_args``) may carry credentials: an API key, a
token, a password in a URL (``wss://user:pw@host``). Run metadata, episode names, score rows, aggregates,
variant labels, tables and reports must never contain them. :func:`redact_args` replaces the value of every
key that names a secret with ``"***"`` and strips the user-info from every URL; a configuration without
secrets comes out equal to what went in, so its ``RunConfig.key()`` and episode names never change.
"""

from __future__ import annotations

import re
from urllib.parse import urlsplit, urlunsplit

#: What stands in for a secret value.
REDACTED = "***"
#: Argument names that hold secrets (matched case-insensitively anywhere in the name).
SECRET_KEY = re.compile(
    r"api[_-]?key|apikey|token|passw(?:or)?d|secret|authori[sz]ation|credential|private[_-]?key|cookie|^auth$",
    re.IGNORECASE,
)


def is_secret_key(name: object) -> bool:
    return isinstance(name, str) and SECRET_KEY.search(name) is not None


def strip_userinfo(url: str) -> str:
    """``url`` without ``user:password@`` (``scheme://u:pw@host:1/p`` -> ``scheme://host:1/p``); other text as is."""
    if "://" not in url or "@" not in url:
        return url
    try:
        parts = urlsplit(url)
    except ValueError:
        return url.split("://", 1)[0] + "://" + REDACTED  # unparseable: keep nothing after the scheme
    if "@" not in parts.netloc:
        return url
    return urlunsplit(parts._replace(netloc=parts.netloc.rsplit("@", 1)[1]))


def redact_value(value: object) -> object:
    """``value`` with secrets removed: nested dicts through :func:`redact_args`, URL user-info stripped."""
    if isinstance(value, dict):
        return redact_args(value)
    if isinstance(value, list | tuple):
        return type(value)(redact_value(v) for v in value)
    if isinstance(value, str):
        return strip_userinfo(value)
    return value


def redact_args(args: dict) -> dict:
    """A copy of ``args`` safe to record or show: a secret-named key's text value becomes ``"***"`` (None, numbers
    and empty strings stay: they are not secrets), URLs lose their user-info, nested values likewise."""
    return {
        key: REDACTED if is_secret_key(key) and isinstance(value, str) and value else redact_value(value)
        for key, value in args.items()
    }


def redact_config(config: dict) -> dict:
    """A RunConfig dict (``RunConfig.to_dict()``) with its ``policy_args`` redacted."""
    if isinstance(config.get("policy_args"), dict):
        return {**config, "policy_args": redact_args(config["policy_args"])}
    return config
