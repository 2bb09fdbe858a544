"""The package as a user installs it: the wheel, installed into a fresh virtual environment outside
the checkout, finds every shipped profile's files (that it runs the demo with only its declared
dependencies: tests/test_install.py); and the code's boundaries
(tools/lint.py: the import contracts in pyproject.toml) hold, and would catch a core importing the bus."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import sysconfig
import venv
from collections.abc import Iterator
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tools"))
from lint import CONFIG, contracts, unpack_wheel  # noqa: E402  (tools/ is not a package)

pytestmark = pytest.mark.system


@pytest.fixture(scope="module")
def built(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The wheel, built once, and unpacked (``pip install --target``): the folder holding both."""
    root = tmp_path_factory.mktemp("wheel")
    unpack_wheel(root)
    return root


@pytest.fixture(scope="module")
def fresh_venv(built: Path) -> Iterator[Path]:
    """A new venv with the wheel installed (not editable) and this environment's third-party packages
    visible through a .pth file (torch, MuJoCo: minutes to download again; the checkout is not)."""
    env = built / "venv"
    venv.create(env, with_pip=False)
    site = Path(sysconfig.get_path("purelib", vars={"base": str(env), "platbase": str(env)}))
    deps = Path(sysconfig.get_path("purelib"))
    (site / "dependencies.pth").write_text(f"{deps}\n")
    wheel = next((built / "wheel").glob("ovamos-*.whl"))
    subprocess.run([sys.executable, "-m", "pip", "-q", "--disable-pip-version-check", "--python",
                    str(env / "bin" / "python"), "install", "--no-deps", str(wheel)], check=True)
    yield env
    shutil.rmtree(env, ignore_errors=True)


def _outside(env: Path, tmp_path: Path, *argv: str, timeout: float) -> subprocess.CompletedProcess[str]:
    clean = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}
    return subprocess.run(argv, cwd=tmp_path, capture_output=True, text=True, timeout=timeout,
                          env={**clean, "PATH": f"{env / 'bin'}:{clean.get('PATH', '')}"})


def test_the_installed_wheel_is_not_the_checkout_and_finds_every_shipped_profile(fresh_venv: Path,
                                                                                 tmp_path: Path) -> None:
    probe = ("import json, ovamos; from ovamos.profiles import PROFILE_DIR, check_service_configs, load_profile; "
             "names = sorted(p.stem for p in PROFILE_DIR.glob('*.toml')); "
             "[check_service_configs(load_profile(PROFILE_DIR / f'{n}.toml')) for n in names]; "
             "print(json.dumps({'file': ovamos.__file__, 'profiles': names}))")
    done = _outside(fresh_venv, tmp_path, str(fresh_venv / "bin" / "python"), "-c", probe, timeout=120)
    assert done.returncode == 0, done.stderr
    out = json.loads(done.stdout)
    assert Path(out["file"]).is_relative_to(fresh_venv) and not Path(out["file"]).is_relative_to(REPO)
    assert {"all", "laptop", "robot", "laptop-secure", "robot-secure", "fleet"} <= set(out["profiles"])


def test_the_import_contracts_hold(built: Path) -> None:
    assert contracts(built / "site") == 0


def test_a_core_importing_the_bus_breaks_a_contract(built: Path, tmp_path: Path,
                                                    capfd: pytest.CaptureFixture[str]) -> None:
    site = tmp_path / "site"
    shutil.copytree(built / "site" / "ovamos", site / "ovamos")
    core = site / "ovamos" / "services" / "camera" / "core.py"
    core.write_text(core.read_text() + "\nfrom ovamos.shared.bus import Bus  # a core reaching for Zenoh\n")
    assert contracts(site) == 1
    out = capfd.readouterr().out
    assert "BROKEN" in out and "ovamos.services.camera.core -> ovamos.shared.bus" in out
    assert CONFIG.exists()
