"""Checks of what a user asks for (``lq run`` options, sweep specs), before anything starts.

Each problem is an :class:`InputError` whose message is one line naming the problem and the valid
values; the CLI prints it and exits with code 2, with no traceback and no bag.
"""

from __future__ import annotations

import contextlib
import difflib
import inspect
import sys
import types
import typing

from lq_ros.core.redact import redact_args
from lq_ros.core.suite_constants import NUM_INIT_STATES, NUM_TASKS, STEP_BUDGETS


class InputError(ValueError):
    """A mistake in the user's input; the message is one line with the valid values."""


def did_you_mean(value: object, choices) -> str:
    """`` (did you mean 'x'?)`` for the choice closest to a mistyped ``value``, or "" when none is close."""
    close = difflib.get_close_matches(str(value), [str(c) for c in choices], n=1, cutoff=0.6)
    return f" (did you mean {close[0]!r}?)" if close else ""


def check_choice(what: str, value: object, choices) -> None:
    """``value`` is one of ``choices``, else one line naming them all (and the closest)."""
    if value not in choices:
        raise InputError(
            f"{what}: {value!r} is not one of {', '.join(map(str, choices))}{did_you_mean(value, choices)}"
        )


# -- suites, tasks, init states -----------------------------------------------------------------------------


def num_tasks(suite: str) -> int:
    """Tasks LIBERO ships for ``suite`` (lq_ros.core.suite_constants.NUM_TASKS)."""
    check_suite(suite)
    return NUM_TASKS[suite]


def check_suite(suite: str) -> None:
    if suite not in STEP_BUDGETS:
        raise InputError(
            f"unknown suite {suite!r}{did_you_mean(suite, STEP_BUDGETS)}; known: {', '.join(STEP_BUDGETS)}"
        )


def check_task(suite: str, task: int) -> None:
    n = num_tasks(suite)
    if not 0 <= task < n:
        raise InputError(f"task {task} is out of range: {suite} has tasks 0..{n - 1}")


def check_init(init: int) -> None:
    if not 0 <= init < NUM_INIT_STATES:
        raise InputError(f"init state {init} is out of range: every task has init states 0..{NUM_INIT_STATES - 1}")


# -- policies ------------------------------------------------------------------------------------------------


def policy_class(name: str) -> type:
    """The class a policy name stands for: a registry name or ``package.module:Class``.

    ``package.module:Class`` is trusted input (the module is imported, as the user's own code), and only a
    subclass of ``lq_ros.policies.base.Policy`` is accepted: any other importable callable (``subprocess:Popen``)
    is refused here, before anything calls it (``lq_ros.policies.policy_class``'s refusal as an InputError).
    """
    from lq_ros.policies import REGISTRY
    from lq_ros.policies import policy_class as resolve

    try:
        return resolve(name)
    except (ImportError, ValueError) as exc:
        message = str(exc)
        hint = did_you_mean(name, REGISTRY) if isinstance(name, str) and ":" not in name else ""
        if hint and message.startswith(f"unknown policy {name!r}"):
            message = message.replace(f"unknown policy {name!r}", f"unknown policy {name!r}{hint}", 1)
        raise InputError(message) from None


def policy_arguments(cls: type) -> tuple[dict[str, inspect.Parameter], dict[str, object], bool]:
    """(named parameters, their type hints, whether it takes any other keyword) of a policy's constructor."""
    signature = inspect.signature(cls.__init__)
    params = {
        n: p
        for n, p in list(signature.parameters.items())[1:]  # without self
        if p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY)
    }
    open_ended = any(p.kind is p.VAR_KEYWORD for p in signature.parameters.values())
    try:
        hints = typing.get_type_hints(cls.__init__)
    except Exception:  # noqa: BLE001 - unresolvable annotations: no type checks, construction still checks
        hints = {}
    return params, hints, open_ended


def describe_arguments(params: dict[str, inspect.Parameter], hints: dict[str, object]) -> str:
    parts = []
    for name, p in params.items():
        text = name + (f": {_type_name(hints[name])}" if name in hints else "")
        if p.default is not p.empty:
            text += f" = {p.default!r}"
        parts.append(text)
    return ", ".join(parts) or "none"


def check_policy_args(name: str, args: dict) -> None:
    """Every argument is one the policy's constructor takes, of the annotated type."""
    cls = policy_class(name)
    params, hints, open_ended = policy_arguments(cls)
    accepted = describe_arguments(params, hints)
    for key, value in args.items():
        if key not in params:
            if open_ended:
                continue
            raise InputError(f"policy {name!r} takes no argument {key!r}; its arguments: {accepted}")
        if key in hints and not _matches(value, hints[key]):
            raise InputError(
                f"policy {name!r}: {key}={redact_args({key: value})[key]!r} is {_article(type(value).__name__)}, not "
                f"{_type_name(hints[key])}; its arguments: {accepted}"
            )


def check_policy(name: str, args: dict) -> None:
    """The policy exists, takes these arguments, and accepts their values (it is built once and closed)."""
    check_policy_args(name, args)
    from lq_ros.policies import make_policy

    try:
        with contextlib.redirect_stdout(sys.stderr):
            make_policy(name, **args).close()
    except Exception as exc:  # noqa: BLE001 - whatever the constructor refuses is the user's input
        cls = policy_class(name)
        params, hints, _ = policy_arguments(cls)
        message = " ".join(str(exc).split()) or type(exc).__name__
        raise InputError(
            f"policy {name!r} refuses {_args_text(args)}: {message}; its arguments: {describe_arguments(params, hints)}"
        ) from None


def check_run(cfg) -> None:
    """Everything about one episode's configuration that can be checked before it starts."""
    check_suite(cfg.suite)
    check_task(cfg.suite, cfg.task)
    check_init(cfg.init)
    check_policy(cfg.policy, cfg.policy_args)


# -- annotations ---------------------------------------------------------------------------------------------


def _matches(value, annotation) -> bool:
    """Whether a JSON-like value (as parsed from the command line or YAML) fits a type annotation."""
    if annotation is typing.Any or annotation is inspect.Parameter.empty:
        return True
    origin = typing.get_origin(annotation)
    if origin in (typing.Union, types.UnionType):
        return any(_matches(value, a) for a in typing.get_args(annotation))
    if origin is typing.Literal:
        return value in typing.get_args(annotation)
    if annotation is type(None):
        return value is None
    if annotation is bool:
        return isinstance(value, bool)
    if annotation is int:
        return isinstance(value, int) and not isinstance(value, bool)
    if annotation is float:
        return isinstance(value, int | float) and not isinstance(value, bool)
    if origin in (list, tuple, set, frozenset, typing.Sequence) or annotation in (list, tuple):
        if not isinstance(value, list | tuple):
            return False
        item_types = typing.get_args(annotation)
        if origin is tuple or not item_types or item_types[-1] is Ellipsis:
            item_types = item_types[:1]
        return not item_types or all(_matches(v, item_types[0]) for v in value)
    if origin is dict or annotation is dict:
        return isinstance(value, dict)
    if isinstance(annotation, type):
        return isinstance(value, annotation)
    return True


def _type_name(annotation) -> str:
    if isinstance(annotation, type) and not typing.get_args(annotation):
        return annotation.__name__
    return str(annotation).replace("typing.", "").replace("NoneType", "None")


def _article(word: str) -> str:
    return ("an " if word[:1] in "aeiou" else "a ") + word


def _args_text(args: dict) -> str:
    return ", ".join(f"{k}={v!r}" for k, v in redact_args(args).items()) or "no arguments"
