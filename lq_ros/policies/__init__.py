"""Policy registry: a policy is chosen by name and keyword parameters."""

from __future__ import annotations

import importlib

from lq_ros.core.merge import ActionPrefix
from lq_ros.policies.base import Policy, PolicyError, ReferenceProtocol
from lq_ros.policies.openpi_remote import libero_state_8d, libero_training_image

#: name -> "module:Class". Adding a policy is one new module and one line here.
REGISTRY: dict[str, str] = {
    "scripted": "lq_ros.policies.scripted:ScriptedExpert",
    "sine": "lq_ros.policies.sine:SinePolicy",
    "faulty": "lq_ros.policies.faulty:FaultyPolicy",
    "openpi": "lq_ros.policies.openpi_remote:OpenPIPolicy",
    "openvla": "lq_ros.policies.openvla_rest:OpenVLARestPolicy",
    "lerobot": "lq_ros.policies.lerobot_client:LeRobotPolicy",
    "oft": "lq_ros.policies.oft:OFTPolicy",
    "flow": "lq_ros.policies.flow:FlowPolicy",
}


def is_registered(name: str) -> bool:
    """Whether ``name`` is a registry name (one of ours), not a user's ``package.module:Class``."""
    return name in REGISTRY


def policy_class(name: str) -> type[Policy]:
    """The class of a registered policy, or of any ``package.module:Class``, without instantiating it.

    ``package.module:Class`` is trusted input (its module is imported: code runs), but only a class that
    subclasses :class:`Policy` is accepted, so no other importable callable (``subprocess:Popen``) is ever
    called with the policy arguments: anything else is refused before it is called (ValueError, one line; a
    module that cannot be imported: ImportError, one line). ``lq_ros.run.validation.policy_class`` gives the same
    refusals as the user's input errors.
    """
    known = f"known: {', '.join(sorted(REGISTRY))} or package.module:Class (a subclass of {Policy.__module__}.Policy)"
    target = REGISTRY.get(name, name)
    module_name, sep, cls_name = target.partition(":")
    if not sep or not module_name or not cls_name or ":" in cls_name:
        raise ValueError(f"unknown policy {name!r}; {known}")
    try:
        module = importlib.import_module(module_name)
    except ImportError as exc:
        raise ImportError(f"policy {name!r}: cannot import module {module_name!r} ({exc}); {known}") from exc
    obj = getattr(module, cls_name, None)
    if obj is None:
        raise ValueError(f"policy {name!r}: module {module_name!r} has no class {cls_name!r}; {known}")
    if not (isinstance(obj, type) and issubclass(obj, Policy)):
        what = "nothing" if obj is None else f"{type(obj).__name__} {obj!r}"[:120]
        raise ValueError(f"policy {name!r} is not a Policy class ({module_name}:{cls_name} is {what}); {known}")
    return obj


def make_policy(name: str, **params) -> Policy:
    """Instantiate a registered policy, or any ``package.module:Class`` (a user's own policy)."""
    return policy_class(name)(**params)


def reference_protocol(name: str, params: dict) -> ReferenceProtocol:
    """The reference protocol a policy made with ``params`` declares (:meth:`Policy.reference`). The policy is made
    and closed again: none of the shipped ones connects or starts a server before its first inference."""
    policy = make_policy(name, **params)
    try:
        return policy.reference()
    finally:
        policy.close()


def declared_replan_steps(name: str, params: dict) -> int:
    """The actions per chunk a policy's reference protocol executes in sync. A policy that does not override
    :meth:`Policy.reference` declares the paper's without being made; one that does is made (and closed)."""
    if policy_class(name).reference is Policy.reference:
        return ReferenceProtocol().replan_steps
    return reference_protocol(name, params).replan_steps


__all__ = [
    "ActionPrefix", "Policy", "PolicyError", "REGISTRY", "ReferenceProtocol", "is_registered", "libero_state_8d",
    "libero_training_image", "make_policy", "policy_class", "reference_protocol", "declared_replan_steps",
]  # fmt: skip
