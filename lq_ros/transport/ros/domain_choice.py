"""Which ROS domain ``lq run`` puts its nodes in: ``--domain-id``, else an exported ``ROS_DOMAIN_ID``, else a free one.

A user who exported ``ROS_DOMAIN_ID`` wants their ROS tools (``ros2 topic echo``, rqt) to see the run's nodes, so
the exported id is honoured like ``--domain-id``: taken unless another lq run of this user holds it (then refused
in one line, lq_ros.transport.ros.reservations.reserved_domain). Without either, a free id is picked (DOMAIN_IDS), so
concurrent runs never hear each other. Sweeps always pick free ids: their workers run at the same time.
"""

from __future__ import annotations

import os
from collections.abc import Mapping

#: The environment variable ROS reads the domain id from.
DOMAIN_ENV = "ROS_DOMAIN_ID"
#: The largest id Fast DDS can use on Linux (its discovery port 7400 + 250 * id stays below 65536).
MAX_DOMAIN_ID = 232


def check_domain_id(value: int, where: str) -> int:
    """``value`` if it is a usable domain id, else ValueError (one line naming ``where`` it came from)."""
    if not 0 <= value <= MAX_DOMAIN_ID:
        raise ValueError(f"{where} {value} is not a ROS domain id: expected 0..{MAX_DOMAIN_ID}")
    return value


def choose_domain(flag: int | None, environ: Mapping[str, str] | None = None) -> tuple[int | None, str]:
    """(domain id or None for a free one, where it came from: ``--domain-id``, ``ROS_DOMAIN_ID`` or ``a free one``)."""
    if flag is not None:
        return check_domain_id(flag, "--domain-id"), "--domain-id"
    text = (os.environ if environ is None else environ).get(DOMAIN_ENV, "").strip()
    if not text:
        return None, "a free one"
    try:
        value = int(text)
    except ValueError:
        raise ValueError(
            f"{DOMAIN_ENV}={text!r} is not a ROS domain id: expected a whole number 0..{MAX_DOMAIN_ID} "
            "(or unset it: lq run then picks a free one)"
        ) from None
    return check_domain_id(value, DOMAIN_ENV), DOMAIN_ENV
