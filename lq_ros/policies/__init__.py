"""Policy registry: a policy is chosen by name and keyword parameters."""

from __future__ import annotations

import importlib

from lq_ros.core.merge import ActionPrefix
from lq_ros.policies.base import Policy, PolicyError

#: name -> "module:Class". Adding a policy is one new module and one line here.
REGISTRY: dict[str, str] = {
    "scripted": "lq_ros.policies.scripted:ScriptedExpert",
    "sine": "lq_ros.policies.sine:SinePolicy",
    "faulty": "lq_ros.policies.faulty:FaultyPolicy",
    "openpi": "lq_ros.policies.openpi_remote:OpenPIPolicy",
    "openvla": "lq_ros.policies.openvla_rest:OpenVLARestPolicy",
    "oft": "lq_ros.policies.oft:OFTPolicy",
    "flow": "lq_ros.policies.flow:FlowPolicy",
}


def policy_class(name: str) -> type[Policy]:
    """The class of a registered policy, or of any ``package.module:Class``, without instantiating it."""
    target = REGISTRY.get(name, name)
    if ":" not in target:
        raise ValueError(f"unknown policy {name!r}; known: {', '.join(sorted(REGISTRY))} or 'module:Class'")
    module, cls = target.split(":")
    return getattr(importlib.import_module(module), cls)


def make_policy(name: str, **params) -> Policy:
    """Instantiate a registered policy, or any ``package.module:Class`` (a user's own policy)."""
    return policy_class(name)(**params)


__all__ = ["ActionPrefix", "Policy", "PolicyError", "REGISTRY", "make_policy", "policy_class"]
