"""``ovamos doctor``: this machine's ``all`` profile passes; a missing weights folder, a missing
serial port, no router at the other end and a clock 30 s off each fail with their fix; weights
that are there load and are timed."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import pytest

from ovamos.doctor import CHRONY_FIX, DoctorOptions, diagnose
from ovamos.profiles import PROFILE_DIR
from ovamos.shared.bus import Bus
from ovamos.shared.bus.zconfig import build_config, open_session
from ovamos.shared.procs import free_port, loopback
from tests.polling import wait_for

pytestmark = pytest.mark.system  # processes and routers: make test-all


def doctor(*args: str, env: dict[str, str] | None = None, cwd: Path | None = None) -> tuple[int, dict[str, dict]]:
    """``ovamos doctor ARGS --json``: its exit code and its checks by name."""
    done = subprocess.run([sys.executable, "-m", "ovamos.cli", "doctor", *args, "--json"], capture_output=True,
                          text=True, timeout=300, env={**os.environ, **(env or {})}, cwd=cwd)
    assert done.stdout, done.stderr
    report = json.loads(done.stdout)
    assert report["ok"] == (done.returncode == 0)
    return done.returncode, {c["name"]: c for c in report["checks"]}


def test_the_all_profile_passes_here(tmp_path: Path) -> None:
    code, checks = doctor("all", cwd=tmp_path)
    assert code == 0, checks
    assert checks["extras"]["status"] == "pass" and "mujoco" in checks["extras"]["detail"]
    assert checks["base"]["status"] == "pass" and checks["disk"]["status"] == "pass"


def test_missing_weights_fail_with_the_download_command_and_present_ones_are_timed(tmp_path: Path) -> None:
    code, checks = doctor("laptop", "--no-load-models", env={"OVAMOS_MODELS": str(tmp_path / "none")})
    assert code == 1
    itm = checks["weights: BLIP ITM"]
    assert itm["status"] == "fail" and f"{tmp_path / 'none' / 'blip-itm-base-coco'} does not exist" in itm["detail"]
    assert f"hf download Salesforce/blip-itm-base-coco --local-dir {tmp_path / 'none' / 'blip-itm-base-coco'}" \
        in itm["fix"]
    from ovamos.bench.random_models import save_model_dirs
    config = save_model_dirs(tmp_path / "built")  # tiny models, random weights, through save_pretrained
    models = tmp_path / "models"
    models.mkdir()
    for directory, name in ((config.itm_dir, "blip-itm-base-coco"), (config.detector_dir, "grounding-dino-tiny"),
                            (config.segmenter_dir, "sam-vit-base")):
        directory.rename(models / name)
    code, checks = doctor("laptop", env={"OVAMOS_MODELS": str(models)})
    assert all(checks[f"weights: {w}"]["status"] == "pass" for w in ("BLIP ITM", "GroundingDINO", "SAM"))
    timed = checks["models"]  # loaded and run: pass, or warn where a frame takes over a second (a loaded CPU)
    assert timed["status"] in ("pass", "warn") and re.search(r"[\d.]+ frames/s on cpu", timed["detail"]), timed


def test_a_missing_serial_port_fails_naming_it(tmp_path: Path) -> None:
    config = (PROFILE_DIR.parent / "services" / "base_driver-kobuki.toml").read_text()
    assert 'port = "/dev/kobuki"' in config
    (tmp_path / "base.toml").write_text(config.replace('port = "/dev/kobuki"', 'port = "/dev/ttyNOPE"'))
    (tmp_path / "robot.toml").write_text(
        f'robot_id = "robot1"\n[[services]]\nservice = "base_driver"\nconfig = "{tmp_path / "base.toml"}"\n')
    code, checks = doctor(str(tmp_path / "robot.toml"))
    assert code == 1
    assert checks["base"]["status"] == "fail" and "/dev/ttyNOPE does not exist" in checks["base"]["detail"]
    assert "ls /dev/serial/by-id/" in checks["base"]["fix"]


def test_no_router_at_the_other_end_fails_with_what_to_start_there() -> None:
    code, checks = doctor("robot", "--other-host", f"127.0.0.1:{free_port()}")
    assert code == 1
    assert checks["link"]["status"] == "fail" and "no Zenoh router answered" in checks["link"]["detail"]
    assert "--listen-link" in checks["link"]["fix"] and "7447" in checks["link"]["fix"]


def test_a_clock_30_s_off_fails_with_chrony_and_a_synced_one_passes() -> None:
    endpoint = loopback(free_port())
    router = open_session(build_config("router", listen=[endpoint]))
    remote = Bus.open(build_config(connect=[endpoint]), "robot1", "planner")  # the other host's service
    try:
        options = DoctorOptions(other_host=endpoint.removeprefix("tcp/"), load_models=False)

        def clock() -> dict:
            return next(c for c in diagnose("all", options) if c.name == "clock").__dict__

        synced = wait_for(lambda: (c := clock())["status"] != "skip" and c, what="the service's clock answered")
        assert synced["status"] == "pass"
        remote.wall_clock = lambda: time.time() + 30.0
        off = clock()
        assert off["status"] == "fail" and off["fix"] == CHRONY_FIX
        (ms,) = re.findall(r"clock is \+([\d.]+) ms", off["detail"])
        assert float(ms) == pytest.approx(30_000, abs=100)
    finally:
        remote.close()
        router.close()
