"""The README's own-policy command works on a copy of the template outside the repository: its bags never land in
the checkout (the template's folder would collect a bags/ of its own)."""

from __future__ import annotations

import re
from pathlib import Path

README = Path(__file__).resolve().parents[1] / "README.md"


def test_the_template_runs_from_a_folder_of_the_users_own():
    blocks = re.findall(r"```bash\n(.*?)```", README.read_text(), re.S)
    [block] = [b for b in blocks if "my_policy:MyPolicy" in b]
    assert "cp examples/my_policy.py" in block and "cd examples" not in block
    assert README.stat().st_size < 12_000
