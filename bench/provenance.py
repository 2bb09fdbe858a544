"""Which code a benchmark result came from.

A search run can be resumed, and grown by policies or episodes, long after it started, on code
that changed in between; its tables then hold episodes of several versions. Each episode's
timing line names the version that ran it, and the summary counts them, so a reader can tell
whether a table is one code's and which episodes to re-run when it is not.
"""

from __future__ import annotations

import hashlib
import os
import subprocess
from pathlib import Path

from ovamos import __version__

#: the checkout this package was imported from, when it is one
REPO = Path(__file__).resolve().parent.parent


def code_version(root: Path = REPO) -> str:
    """The git commit of ``root`` (``-dirty`` and a digest of the changes, when there are any), or,
    where ``root`` is not a git checkout or git is not installed (an installed wheel, a copied
    tree), the package version and a digest of the Python sources under ``root``: two copies of
    different code never share a name, which the report-seed check of ``bench compare`` relies on."""
    if (root / ".git").exists():
        try:
            out = subprocess.run(["git", "-C", str(root), "describe", "--always", "--dirty", "--abbrev=12"],
                                 capture_output=True, text=True, timeout=30, check=True).stdout.strip()
            if out.endswith("-dirty"):
                diff = subprocess.run(["git", "-C", str(root), "diff", "HEAD"], capture_output=True, timeout=30,
                                      check=True).stdout
                out += "-" + hashlib.sha256(diff).hexdigest()[:8]
            return out
        except (OSError, subprocess.SubprocessError):
            pass
    return f"ovamos {__version__}+{_sources_digest(root)}"


_NOT_SOURCES = {"tests", "docs", "site", "build", "node_modules", "__pycache__"}


def _sources_digest(root: Path) -> str:
    """Eight hex digits of the ``.py`` files under ``root`` (their paths and bytes; symbolic links
    followed, hidden folders, tests and docs left out)."""
    digest = hashlib.sha256()
    for folder, dirs, files in os.walk(root, followlinks=True):
        dirs[:] = sorted(d for d in dirs if not d.startswith(".") and d not in _NOT_SOURCES)
        for name in sorted(f for f in files if f.endswith(".py")):
            path = Path(folder, name)
            digest.update(str(path.relative_to(root)).encode() + b"\0" + path.read_bytes())
    return digest.hexdigest()[:8]
