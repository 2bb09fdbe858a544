"""Which code a benchmark result came from.

A search run can be resumed, and grown by policies or episodes, long after it started, on code
that changed in between; its tables then hold episodes of several versions. Each episode's
timing line names the version that ran it, and the summary counts them, so a reader can tell
whether a table is one code's and which episodes to re-run when it is not.
"""

from __future__ import annotations

import subprocess
from pathlib import Path

from ovamos import __version__

#: the checkout this package was imported from, when it is one
REPO = Path(__file__).resolve().parent.parent


def code_version(root: Path = REPO) -> str:
    """The git commit of ``root`` (``-dirty`` with uncommitted changes), or the package version
    where ``root`` is not a git checkout or git is not installed (an installed wheel)."""
    if (root / ".git").exists():
        try:
            out = subprocess.run(["git", "-C", str(root), "describe", "--always", "--dirty", "--abbrev=12"],
                                 capture_output=True, text=True, timeout=30, check=True)
            return out.stdout.strip()
        except (OSError, subprocess.SubprocessError):
            pass
    return f"ovamos {__version__}"
