"""The checks CI runs on the code itself: ruff, the import contracts (import-linter) and mypy on the
cores, each configured in pyproject.toml.

import-linter and mypy find a package by its folder, and this one's folders are mapped into it
(``shared/`` is ``ovamos.shared``: setup.py), so both run on the wheel's layout: the package is
built and unpacked into a temporary folder first (a few seconds, nothing installed anywhere).

    python tools/lint.py            # all three; exit 1 naming the check that failed
    python tools/lint.py contracts  # one of: ruff, contracts, types
"""

from __future__ import annotations

import argparse
import fcntl
import hashlib
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
CONFIG = REPO / "pyproject.toml"
BIN = Path(sys.executable).parent
CHECKS = ("ruff", "contracts", "types")


PIP = [sys.executable, "-m", "pip", "-q", "--disable-pip-version-check"]


def build_wheel(into: Path) -> Path:
    """The package's wheel, built into ``into``.

    setuptools stages the files in the checkout's ``build/`` and packs whatever it finds there, so a
    module removed since the last build would ride along: the folder goes before and after. Builds
    take turns (a lock beside the temporary files): parallel test workers share the one ``build/``."""
    lock = Path(tempfile.gettempdir()) / f"ovamos-build-{hashlib.sha1(str(REPO).encode()).hexdigest()[:12]}.lock"
    with lock.open("w") as held:
        fcntl.flock(held, fcntl.LOCK_EX)
        shutil.rmtree(REPO / "build", ignore_errors=True)
        try:
            subprocess.run([*PIP, "wheel", "--no-deps", "--no-build-isolation", "-w", str(into), str(REPO)],
                           check=True, cwd=into.parent)
        finally:
            shutil.rmtree(REPO / "build", ignore_errors=True)
    (wheel,) = into.glob("ovamos-*.whl")
    return wheel


def unpack_wheel(into: Path) -> Path:
    """Build the package's wheel (:func:`build_wheel`, in ``into/wheel``) and unpack it (``pip install
    --target``) under ``into``; the site folder."""
    into.mkdir(parents=True, exist_ok=True)
    wheel, site = build_wheel(into / "wheel"), into / "site"
    subprocess.run([*PIP, "install", "--no-deps", "--no-compile", "--target", str(site), str(wheel)],
                   check=True, cwd=into)
    return site


def ruff() -> int:
    return subprocess.run([str(BIN / "ruff"), "check", str(REPO)], cwd=REPO).returncode


def contracts(site: Path) -> int:
    return subprocess.run([str(BIN / "lint-imports"), str(CONFIG)], cwd=site,
                          env={**os.environ, "PYTHONPATH": str(site)}).returncode


def types(site: Path) -> int:
    return subprocess.run([sys.executable, "-m", "mypy", "--config-file", str(CONFIG)], cwd=site,
                          env={**os.environ, "MYPYPATH": str(site)}).returncode


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("checks", nargs="*", metavar="{ruff,contracts,types}", help="the checks to run (default: all)")
    checks = parser.parse_args(argv).checks or list(CHECKS)
    if unknown := sorted(set(checks) - set(CHECKS)):
        parser.error(f"unknown check {', '.join(unknown)}: one of {', '.join(CHECKS)}")
    failed = []
    with tempfile.TemporaryDirectory(prefix="ovamos-lint-") as tmp:
        site = unpack_wheel(Path(tmp)) if {"contracts", "types"} & set(checks) else Path(tmp)
        for check in checks:
            print(f"== {check}", flush=True)
            code = ruff() if check == "ruff" else contracts(site) if check == "contracts" else types(site)
            if code:
                failed.append(check)
    if failed:
        print(f"failed: {', '.join(failed)}", file=sys.stderr)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
