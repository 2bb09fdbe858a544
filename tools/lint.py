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


def unpack_wheel(into: Path) -> Path:
    """Build the package's wheel and unpack it (``pip install --target``) under ``into``; the site folder.

    setuptools stages the files in the checkout's ``build/`` and packs whatever it finds there, so a
    module removed since the last build would ride along: the folder goes before and after."""
    wheels, site = into / "wheel", into / "site"
    pip = [sys.executable, "-m", "pip", "-q", "--disable-pip-version-check"]
    shutil.rmtree(REPO / "build", ignore_errors=True)
    try:
        subprocess.run([*pip, "wheel", "--no-deps", "--no-build-isolation", "-w", str(wheels), str(REPO)],
                       check=True, cwd=into)
    finally:
        shutil.rmtree(REPO / "build", ignore_errors=True)
    subprocess.run([*pip, "install", "--no-deps", "--no-compile", "--target", str(site), *map(str, wheels.glob("*.whl"))],
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
