"""Where the deployment files are: the ``deploy/`` folder of a checkout, or the same files inside an
installed wheel (package ``ovamos.deploy``), so ``ovamos demo`` and ``ovamos up`` run from either."""

from __future__ import annotations

from importlib.resources import files
from pathlib import Path

__all__ = ["DEPLOY_DIR", "PROFILE_DIR", "shipped_profiles"]

#: the folder holding ``profiles/``, ``services/``, ``zenoh/``, ``ros2/`` and ``foxglove/`` (a real folder:
#: the profiles name their files by relative paths, and DDS and Zenoh read files by path)
DEPLOY_DIR = Path(str(files("ovamos.deploy")))
PROFILE_DIR = DEPLOY_DIR / "profiles"


def shipped_profiles() -> list[str]:
    """The shipped profiles' names (``ovamos up NAME``), from the folder: none is left out of a list."""
    return sorted(p.stem for p in PROFILE_DIR.glob("*.toml"))
