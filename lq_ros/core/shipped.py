"""Files the package ships from the top level of the source tree, where their one copy lives.

``msg_schemas/`` (the message definitions, also the input of the lq_msgs cmake build), ``config/robots/`` (the
shipped robot interfaces) and ``config/dds/`` (the stack's Fast DDS profile) stay at the top level of the source
tree. Building a wheel copies them into the package (``lq_ros/_shipped/``, setup.py), so an installed ``lq_ros``
finds them without the source tree; a source checkout (an editable install) reads them in place.
"""

from __future__ import annotations

from pathlib import Path

#: The installed package's folder (``lq_ros/``).
PACKAGE_DIR = Path(__file__).resolve().parents[1]
#: The source tree's root in a checkout (above the installed package, it is site-packages).
REPO_ROOT = PACKAGE_DIR.parent
#: Where a built package holds the shipped folders, each under its path in the source tree.
SHIPPED_DIR = PACKAGE_DIR / "_shipped"
#: The shipped folders (paths from the source tree's root) and the files of each that are shipped; setup.py reads it.
SHIPPED = {"msg_schemas/lq_msgs/msg": "*.msg", "config/robots": "*.yaml", "config/dds": "*.xml"}


def shipped_path(relative: str) -> Path:
    """A shipped folder (a key of SHIPPED): the installed package's copy, else the source tree's."""
    installed = SHIPPED_DIR / relative
    return installed if installed.is_dir() else REPO_ROOT / relative
