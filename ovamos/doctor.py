"""``ovamos doctor [PROFILE]``: one host checked as a profile will use it, before the first search.

Each check says pass, warn, fail or skip (nothing of the profile needs it), what it found, and
the command or step that fixes it: the Python extras the profile's services import; torch and the
GPU, the perception weights where the config says, loaded and timed on this device; the camera and
the base as their configs name them (a RealSense enumerates, a serial port exists and is writable,
a CAN interface is up); the router's port; the other host's router, and this clock against the
other host's services (over Zenoh, as NTP measures it); certificates; disk for logs and
recordings. A check never starts a service or moves the robot.
"""

from __future__ import annotations

import importlib.util
import os
import shutil
import socket
import statistics
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Literal

from ovamos.profiles import (
    DEFAULT_CERTS,
    Profile,
    ProfileError,
    check_certs,
    laptop_endpoint,
    load_profile,
    resolve_profile,
    tcp_address,
)

__all__ = ["Check", "DoctorOptions", "diagnose", "clock_offset"]

Status = Literal["pass", "warn", "fail", "skip"]

TORCH_FIX = "pip install torch==2.13.0 (CUDA; CPU only: --index-url https://download.pytorch.org/whl/cpu), " \
            "see docs/getting-started.md#torch"
ROS_FIX = "source /opt/ros/jazzy/setup.bash, in a venv made with --system-site-packages (docs/deploying/ros2.md)"
CHRONY_FIX = "sync both clocks: sudo apt install chrony on both hosts, the robot's /etc/chrony/chrony.conf with " \
             "'server <laptop-ip> iburst', the laptop's with 'allow <robot-subnet>' (docs/deploying/first-run.md)"


@dataclass(frozen=True)
class Check:
    """One check's verdict: ``detail`` what was found, ``fix`` what to do about it (empty on pass)."""

    name: str
    status: Status
    detail: str
    fix: str = ""


@dataclass(frozen=True)
class DoctorOptions:
    """``other_host``: HOST:PORT of the other host's router (the laptop's, from the robot: the
    ``--connect-laptop`` address); ``load_models``: load the perception weights and time them
    (seconds to a minute); ``max_clock_offset_s``: the most the two clocks may disagree."""

    other_host: str | None = None
    certs: Path | None = None
    load_models: bool = True
    max_clock_offset_s: float = 0.1
    state_dir: Path = Path("state")
    min_free_gb: float = 5.0
    timeout_s: float = 3.0


def diagnose(profile: str | Path, options: DoctorOptions) -> list[Check]:
    """Every check of this host for ``profile`` (a shipped name or a file)."""
    try:
        loaded = load_profile(resolve_profile(profile))
    except ProfileError as exc:
        return [Check("profile", "fail", str(exc), "ovamos up --help lists the shipped profiles")]
    configs, checks = _configs(loaded)
    checks += [_extras(configs)]
    perception = next((c for s, c in configs if s == "perception" and c.backend == "hf"), None)
    checks += _perception(perception, options) if perception is not None else \
        [Check("perception", "skip", "no perception with real models in this profile")]
    checks += [_camera(configs, options.timeout_s), _base(configs, options.timeout_s), _router_port(loaded),
               *_link(options),
               _certificates(loaded, options), _disk(options)]
    return checks


def _configs(profile: Profile) -> tuple[list[tuple[str, Any]], list[Check]]:
    from ovamos.profiles import service_config
    from ovamos.registry import UnknownServiceError
    from ovamos.shared.service import ServiceConfigError
    configs, problems = [], []
    for spec in profile.services:
        try:
            configs.append((spec.service, service_config(spec)))
        except (UnknownServiceError, ServiceConfigError, ImportError) as exc:
            problems.append(f"{spec.entry_name}: {exc}")
    if problems:
        return configs, [Check("configs", "fail", "; ".join(problems), "fix the config file named")]
    return configs, [Check("configs", "pass", f"{len(configs)} service configs of {profile.source.name} valid")]


def _extras(configs: list[tuple[str, Any]]) -> Check:
    """The modules the profile's services import, by the extra (or ROS install) that brings them."""
    needed: dict[str, str] = {}
    for service, config in configs:
        if service == "sim":
            needed["mujoco"] = "pip install 'ovamos[sim]'"
        elif service == "perception" and config.backend == "hf":
            needed.update(torch=TORCH_FIX, transformers="pip install 'ovamos[perception]'",
                          PIL="pip install 'ovamos[perception]'")
        elif service == "camera" and config.backend == "realsense":
            needed["pyrealsense2"] = "pip install 'ovamos[camera]' (and apt install libusb-1.0-0)"
        elif (service == "camera" and config.backend == "ros2") or service == "rosview" or \
                (service == "base_driver" and config.driver.hardware == "ros2"):
            needed["rclpy"] = ROS_FIX
    missing = {module: fix for module, fix in needed.items() if importlib.util.find_spec(module) is None}
    if missing:
        return Check("extras", "fail", f"missing: {', '.join(missing)}", "; ".join(dict.fromkeys(missing.values())))
    return Check("extras", "pass", f"{', '.join(needed) or 'the base install'}: importable")


def _perception(config: Any, options: DoctorOptions) -> list[Check]:
    """torch's device, the weights where the config says, and (``load_models``) a timed pass."""
    from ovamos.services.perception.hf.loading import DETECTOR, ITM, SEGMENTER, ModelFilesError, model_type
    hf = config.hf
    try:
        import torch
    except ImportError:
        return [Check("torch", "fail", "torch is not installed", TORCH_FIX)]
    if torch.cuda.is_available():
        props = torch.cuda.get_device_properties(0)
        checks = [Check("torch", "pass", f"torch {torch.__version__} on {props.name} "
                                         f"({props.total_memory / 2**30:.0f} GiB)")]
    else:
        checks = [Check("torch", "fail" if hf.device == "cuda" else "warn",
                        f"torch {torch.__version__} sees no CUDA device: perception runs on the CPU, "
                        "seconds a frame", f"check nvidia-smi; {TORCH_FIX}")]
    complete = True
    for role, directory in ((ITM, hf.itm_dir), (DETECTOR, hf.detector_dir), (SEGMENTER, hf.segmenter_dir)):
        folder = hf.folder(directory)
        try:
            model_type(role, folder)
            checks.append(Check(f"weights: {role.what}", "pass", f"complete in {folder}"))
        except ModelFilesError as exc:
            complete = False
            checks.append(Check(f"weights: {role.what}", "fail", str(exc).split("; ")[0],
                                f"hf download {role.repo} --local-dir {folder} (on a machine with internet "
                                f"access, then copy the folder here; or set {role.config_key})"))
    if complete and options.load_models:
        checks.append(_timed_pass(config))
    return checks


def _timed_pass(config: Any) -> Check:
    """The three models loaded as the service loads them, and a 640 x 480 frame scored and detected."""
    from ovamos.services.diag.testpattern import pattern_frame
    from ovamos.services.perception.errors import BackendError
    from ovamos.services.perception.hf.backend import HfBackend
    try:
        backend = HfBackend.load(config.hf)
        frame, targets = pattern_frame(0, time.time()), ["chair", "cup", "bed"]
        times = []
        for _ in range(4):
            start = time.perf_counter()
            backend.score(frame, targets)
            backend.detect(frame, targets)
            times.append(time.perf_counter() - start)
        del times[0]  # the first pass warms the device up
    except (BackendError, RuntimeError, OSError) as exc:
        return Check("models", "fail", f"loading or running the models failed: {exc}",
                     "re-download the folder named (docs/deploying/index.md#perception-weights)")
    fps = 1 / statistics.median(times)
    device = backend.placement.device
    memory = ""
    if device == "cuda":
        import torch
        memory = f", {torch.cuda.max_memory_allocated() / 2**30:.1f} GiB of GPU memory at the peak"
    return Check("models", "pass" if fps >= 1 else "warn", f"{fps:.1f} frames/s on {device} (score + detect, "
                 f"3 targets, 640x480){memory}", "" if fps >= 1 else "a GPU: the search waits for every frame")


def _camera(configs: list[tuple[str, Any]], timeout_s: float) -> Check:
    config = next((c for s, c in configs if s == "camera"), None)
    if config is None:
        return Check("camera", "skip", "no camera service in this profile" +
                     ("; the simulated robot renders its own" if any(s == "sim" for s, _ in configs) else ""))
    if config.backend == "realsense":
        try:
            import pyrealsense2 as rs
        except ImportError:
            return Check("camera", "fail", "pyrealsense2 is not installed", "pip install 'ovamos[camera]'")
        found = [d.get_info(rs.camera_info.serial_number) for d in rs.context().query_devices()]
        if not found:
            return Check("camera", "fail", "no RealSense found", "plug it into a USB 3 port; "
                         "rs-enumerate-devices should list it; udev rules: docs/deploying/camera.md")
        return Check("camera", "pass", f"RealSense {', '.join(found)}")
    if config.backend == "file":
        path = Path(config.file.path)
        return Check("camera", "pass" if path.is_file() else "fail", f"recording {path}",
                     "" if path.is_file() else "give [file] path an existing recording")
    if config.backend == "ros2":
        return _ros_camera(config.ros2, timeout_s)
    return Check("camera", "fail", f"the {config.backend} backend is refused (docs/deploying/camera.md)",
                 "backend = \"realsense\", \"ros2\" or \"file\"")


def _ros_camera(config: Any, timeout_s: float) -> Check:
    """A ROS camera's topics: frames arrive, and at what rate (over ``timeout_s``)."""
    from ovamos.services.camera.capture import CameraError
    from ovamos.services.camera.ros2 import Ros2Backend
    backend = Ros2Backend(config)
    try:
        backend.start()
        frames, deadline = 0, time.monotonic() + timeout_s
        first = None
        while time.monotonic() < deadline:
            if backend.read(0.2) is not None:
                frames += 1
                first = first or time.monotonic()
    except CameraError as exc:
        return Check("camera", "fail", str(exc), ROS_FIX)
    finally:
        backend.stop()
    if frames == 0:
        return Check("camera", "fail", f"no frame on {config.color} (with {config.depth} and {config.info}) in "
                     f"{timeout_s:g} s", "is the camera's ROS driver up, with the same ROS_DOMAIN_ID? ros2 topic "
                     f"hz {config.color}; aligned depth needs align_depth.enable:=true (RealSense)")
    rate = (frames - 1) / (time.monotonic() - first) if first is not None and frames > 1 else 0.0
    return Check("camera", "pass", f"frames on {config.color} at {rate:.1f} Hz")


def _base(configs: list[tuple[str, Any]], timeout_s: float) -> Check:
    config = next((c for s, c in configs if s == "base_driver"), None)
    if config is None:
        simulated = any(s == "sim" for s, _ in configs)
        return Check("base", "pass" if simulated else "skip",
                     "the simulated robot" if simulated else "no base in this profile")
    driver = config.driver
    if driver.hardware in ("kobuki", "opencr"):
        port = Path(getattr(driver, driver.hardware).port)
        if not port.exists():
            return Check("base", "fail", f"{driver.hardware}: serial port {port} does not exist",
                         "plug the base in; ls /dev/serial/by-id/ and set [driver." + driver.hardware +
                         "] port (a udev symlink is best)")
        if not os.access(port, os.R_OK | os.W_OK):
            return Check("base", "fail", f"{driver.hardware}: {port} is not readable and writable by this user",
                         "sudo usermod -aG dialout $USER, then log in again")
        return Check("base", "pass", f"{driver.hardware} on {port}")
    if driver.hardware == "odrive_can":
        can = driver.odrive.can
        if can.interface != "socketcan":
            return Check("base", "skip", f"odrive over {can.interface}: not checked here")
        state = Path(f"/sys/class/net/{can.channel}/operstate")
        if not state.exists():
            return Check("base", "fail", f"no CAN interface {can.channel}",
                         "plug the CAN adapter in; ip link shows it (docs/deploying/robot-bases.md)")
        flags = int(Path(f"/sys/class/net/{can.channel}/flags").read_text(), 16)
        if not flags & 0x1:  # IFF_UP
            return Check("base", "fail", f"{can.channel} is down",
                         f"sudo ip link set {can.channel} up type can bitrate {can.bitrate}")
        return Check("base", "pass", f"odrive on {can.channel} (up)")
    if driver.hardware == "ros2":
        return _ros_base(driver.ros2, timeout_s)
    return Check("base", "skip", f"the {driver.hardware} base: not checked here")


def _ros_base(config: Any, timeout_s: float) -> Check:
    """A ROS 2 base: odometry arriving (and its rate), and something subscribed to ``cmd_vel``;
    nothing is sent on it."""
    from ovamos.services.base_driver.hardware import HardwareError
    from ovamos.services.base_driver.ros2.client import Ros2Hardware
    hardware = Ros2Hardware(config)
    try:
        hardware.open()
        time.sleep(timeout_s)  # odometry for timeout_s: its rate
        counts, listeners = hardware.counters(), hardware.cmd_vel_subscribers()
    except HardwareError as exc:
        return Check("base", "fail", str(exc), ROS_FIX)
    finally:
        hardware.close()
    odom, cmd_vel = config.topic(config.odom), config.topic(config.cmd_vel)
    if not counts.get("ros2_odom"):
        return Check("base", "fail", f"no nav_msgs/Odometry on {odom} in {timeout_s:g} s",
                     "is the robot's bringup up, with the same ROS_DOMAIN_ID and namespace? ros2 topic hz " + odom)
    rate = f"odometry on {odom} at {counts['ros2_odom'] / timeout_s:.0f} Hz"
    if listeners == 0:
        return Check("base", "fail", f"{rate}, but nothing subscribes to {cmd_vel}",
                     f"ros2 topic info {cmd_vel}: the base's driver should be there ([driver.ros2] cmd_vel, namespace)")
    return Check("base", "pass", f"{rate}; {cmd_vel} has {listeners} subscriber(s)")


def _router_port(profile: Profile) -> Check:
    """The router's plain listener: free, or taken (by a router already up, or something else)."""
    if profile.router is None:
        return Check("router", "skip", "no router in this profile")
    listen = profile.router.listen or profile.config_listen()
    address = next((a for a in map(tcp_address, listen) if a is not None), None)
    if address is None:
        return Check("router", "skip", "no tcp listener to check")
    host, port = address
    with socket.socket() as probe:
        probe.settimeout(0.5)
        taken = probe.connect_ex((host, port)) == 0
    if taken:
        return Check("router", "warn", f"{host}:{port} is taken: a router already up (ovamos up running?) or "
                     "another program", f"ovamos status --connect tcp/{host}:{port} says whether it is ours")
    return Check("router", "pass", f"{host}:{port} free for the router")


def _link(options: DoctorOptions) -> list[Check]:
    """The other host's router, and this clock against its services'."""
    if options.other_host is None:
        return [Check("link", "skip", "no --other-host HOST:PORT given (the other host's router)")]
    from ovamos.shared.bus.zconfig import ZenohConfigError, build_config, open_session
    try:
        endpoint = laptop_endpoint(options.other_host, option="--other-host")
        session = open_session(build_config("client", connect=[endpoint], open_timeout_s=options.timeout_s))
    except (ProfileError, ZenohConfigError) as exc:
        return [Check("link", "fail", str(exc).split("\n")[0],
                      "on the other host: ovamos up laptop --listen-link <its-ip>:7447; its firewall must let "
                      "TCP 7447 in (docs/deploying/first-run.md)")]
    try:
        offset = clock_offset(session, options.timeout_s)
    finally:
        session.close()
    link = Check("link", "pass", f"the router at {endpoint} answers")
    if offset is None:
        return [link, Check("clock", "skip", "no service answers there yet: start the other host's profile, then "
                            "run this again", "")]
    value, error, host = offset
    detail = f"{host}'s clock is {value * 1e3:+.1f} ms from this one's (+-{error * 1e3:.1f} ms)"
    if abs(value) - error > options.max_clock_offset_s:
        return [link, Check("clock", "fail", detail + f", more than {options.max_clock_offset_s * 1e3:.0f} ms: "
                            "stamps compared across the hosts (latencies, staleness) are off by that", CHRONY_FIX)]
    return [link, Check("clock", "pass", detail)]


def clock_offset(session: Any, timeout_s: float) -> tuple[float, float, str] | None:
    """How far another host's clock is from this one's, over Zenoh as NTP measures it: each
    service's stats answer says its host and its clock when it answered (``now``); against the
    middle of the query's round trip, offset = now - (sent + received) / 2, within half the round
    trip. Answers of another host win over this host's (a rehearsal on one machine has only this
    host); the tightest answer of that host is taken. None: no service answered."""
    from ovamos.shared import keys
    from ovamos.shared.messages import DecodeError, ServiceStats
    here = socket.gethostname()
    found: list[tuple[float, float, str]] = []
    sent = time.time()
    for reply in session.get(keys.stats(keys.ANY), timeout=timeout_s):
        received = time.time()
        if reply.ok is None:
            continue
        try:
            stats = ServiceStats.from_bytes(reply.ok.payload.to_bytes())
        except DecodeError:
            continue
        if stats.now is not None:
            found.append((stats.now - (sent + received) / 2, (received - sent) / 2, stats.host or "?"))
    if not found:
        return None
    others = [f for f in found if f[2] != here] or found
    return min(others, key=lambda f: f[1])


def _certificates(profile: Profile, options: DoctorOptions) -> Check:
    if not profile.secure:
        return Check("certificates", "skip", "not a secure profile")
    try:
        check_certs(profile, options.certs)
    except ProfileError as exc:
        return Check("certificates", "fail", str(exc), "ovamos certs ... (docs/deploying/secure-link.md)")
    return Check("certificates", "pass", f"valid in {options.certs or DEFAULT_CERTS}")


def _disk(options: DoctorOptions) -> Check:
    folder = options.state_dir.resolve()
    probe = next((p for p in (folder, *folder.parents) if p.exists()), Path("/"))
    free = shutil.disk_usage(probe).free / 1e9
    if free < options.min_free_gb:
        return Check("disk", "warn", f"{free:.1f} GB free for logs, maps and recordings in {folder}",
                     f"free {options.min_free_gb:.0f} GB or more (recordings grow with every run)")
    return Check("disk", "pass", f"{free:.0f} GB free in {probe}")


def as_json(checks: list[Check]) -> dict[str, Any]:
    """``--json``: every check, and whether the host is ready (no fail)."""
    return {"ok": all(c.status != "fail" for c in checks), "checks": [asdict(c) for c in checks]}
