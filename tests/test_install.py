"""The documented install lines hold: the README's by-hand line is the Makefile's, every module the
tests import comes with its extras (what collecting them in a fresh venv needs), and a wheel
installed with ``[sim]`` alone, in a fresh virtual environment outside the checkout, runs the demo
and reaches the gateway (its HTTP client is in the base install)."""

from __future__ import annotations

import ast
import os
import re
import subprocess
import sys
import venv
from importlib import metadata
from pathlib import Path

import pytest

from ovamos.shared.procs import free_port

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tools"))
from lint import build_wheel  # noqa: E402  (tools/ is not a package)


def _makefile_extras() -> str:
    (extras,) = re.findall(r"^EXTRAS := (\S+)$", (ROOT / "Makefile").read_text(), re.M)
    return extras


@pytest.mark.parametrize("page", ["README.md", "docs/getting-started.md"])
def test_the_by_hand_install_line_is_the_makefiles(page: str) -> None:
    lines = re.findall(r"pip install -e '\.\[([\w,]+)\]'", (ROOT / page).read_text())
    assert lines and set(lines) == {_makefile_extras()}, (page, lines)


@pytest.mark.system
@pytest.mark.timeout(900)
def test_a_sim_wheel_outside_the_checkout_runs_the_demo_and_submits(tmp_path: Path) -> None:
    wheel = build_wheel(tmp_path / "wheels")
    env = tmp_path / "venv"
    venv.create(env, with_pip=True)
    installed = subprocess.run([str(env / "bin" / "pip"), "install", "-q", "--disable-pip-version-check",
                                "--no-compile", f"{wheel}[sim]"], capture_output=True, text=True, timeout=900)
    assert installed.returncode == 0, installed.stderr[-2000:]
    ovamos = str(env / "bin" / "ovamos")
    clean = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}
    demo = subprocess.run([ovamos, "demo", "--target", "floor_lamp", "--no-record", "--out", str(tmp_path / "demo"),
                           "--timeout", "300"], capture_output=True, text=True, timeout=420, cwd=tmp_path, env=clean)
    assert demo.returncode == 0, (demo.stdout[-1500:], demo.stderr[-1500:])
    assert "done: found floor_lamp" in demo.stdout
    gateway = f"http://127.0.0.1:{free_port()}"  # nothing there: the client runs and says so
    submit = subprocess.run([ovamos, "submit", "chair", "--gateway", gateway], capture_output=True, text=True,
                            timeout=60, cwd=tmp_path, env=clean)
    assert submit.returncode == 2 and f"cannot reach the gateway at {gateway}" in " ".join(submit.stderr.split())
    assert not list(env.glob("lib/python*/site-packages/torch"))  # the demo needs no torch


def test_every_module_the_tests_import_comes_with_the_by_hand_extras() -> None:
    """What a fresh venv with the by-hand line would need to collect the tests: each third-party
    module a test file imports at its top is in a distribution that ``ovamos[EXTRAS]`` requires, or
    one of theirs (psutil was declared nowhere once, and only the cluster extra brought it)."""
    needed = _requirement_closure(_makefile_extras().split(","))
    providers = metadata.packages_distributions()
    first_party = {"ovamos", "tests", "lint", "nodes", *sys.stdlib_module_names, "__future__"}
    missing = {}
    for path in sorted((ROOT / "tests").rglob("*.py")):
        for node in ast.parse(path.read_text()).body:
            names = [a.name for a in node.names] if isinstance(node, ast.Import) else \
                [node.module] if isinstance(node, ast.ImportFrom) and node.module and not node.level else []
            for name in names:
                top = name.split(".")[0]
                if top in first_party:
                    continue
                if not {_canonical(d) for d in providers.get(top, [])} & needed:
                    missing.setdefault(top, []).append(path.name)
    assert not missing, f"imported by tests, brought by no extra of {_makefile_extras()}: {missing}"


def _canonical(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def _requirement_closure(extras: list[str]) -> set[str]:
    """The distributions ``ovamos[extras]`` needs, transitively, as installed here."""
    from packaging.requirements import Requirement
    todo, seen = [("ovamos", tuple(extras))], set()
    while todo:
        name, wanted = todo.pop()
        if _canonical(name) in seen:
            continue
        seen.add(_canonical(name))
        try:
            requires = metadata.requires(name) or []
        except metadata.PackageNotFoundError:
            continue
        for text in requires:
            req = Requirement(text)
            if req.marker is None or any(req.marker.evaluate({"extra": e}) for e in (*wanted, "")):
                todo.append((req.name, tuple(req.extras)))
    return seen
