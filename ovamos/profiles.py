"""Deployment profiles: what ``ovamos up PROFILE`` runs on one host.

A profile (``deploy/profiles/*.toml``) names the router and the services of one
host, each with its config and Zenoh files; :func:`load_profile` validates it
completely (unknown keys, missing files, unknown services) before anything
starts, with errors that name the file and the entry, and
:func:`check_service_configs` checks each service's config file against its
service's model. :func:`supervisor_for` turns a profile into the
:class:`~ovamos.supervisor.Supervisor` that runs it.
"""

from __future__ import annotations

import json
import tomllib
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from pydantic import Field, PrivateAttr, ValidationError, field_validator

from ovamos.registry import SERVICES
from ovamos.shared.config import StrictModel, format_override, merged
from ovamos.shared.deploy import PROFILE_DIR, shipped_profiles
from ovamos.shared.motion import DriveMode
from ovamos.supervisor import DEFAULT_LOG_DIR, Backoff, Entry, Supervisor

DEFAULT_CERTS = Path("state/certs")  # relative to the working directory, like the logs


class ProfileError(ValueError):
    """A profile file that cannot be used; the message names the file and the entry."""


class RouterSpec(StrictModel):
    """The host's Zenoh router (``ovamos router``); paths are relative to the profile file."""

    name: str = "router"
    config: Path | None = None
    listen: list[str] = Field(default_factory=list, description="replace the config's listen endpoints")
    connect: list[str] = Field(default_factory=list, description="replace the config's connect endpoints")
    cert: str | None = Field(default=None, description="this host's certificate (its CN: laptop, robot) "
                                                       "in the folder `ovamos up --certs` names: the "
                                                       "router's tls/ links use it")


class ServiceSpec(StrictModel):
    """One ``ovamos run SERVICE`` process; paths are relative to the profile file."""

    service: str
    name: str | None = Field(default=None, description="unique entry name (log file); default: service")
    config: Path | None = None
    zenoh: Path | None = None
    connect: list[str] = Field(default_factory=list, description="replace the Zenoh file's connect endpoints")
    instance: str = "0"
    robot_id: str | None = Field(default=None, description="default: the profile's robot_id")
    delay_s: float = Field(default=0.0, ge=0, description="start this long after the previous service")

    @property
    def entry_name(self) -> str:
        return self.name or (self.service if self.instance == "0" else f"{self.service}-{self.instance}")


class Profile(StrictModel):
    """What ``ovamos up`` runs on one host.

    ``robots`` makes it a fleet (:mod:`ovamos.fleet`): each per-robot service runs once per
    robot (entry ``NAME-ROBOT``), each fleet-wide one (perception, gateway) once under
    ``robot_id``, told the robots (``ovamos run --set``).
    """

    description: str = ""
    robot_id: str = "robot1"
    robots: list[str] = Field(default_factory=list, description="a fleet's robot ids; empty: one robot, robot_id")
    router: RouterSpec | None = None
    services: list[ServiceSpec] = Field(default_factory=list)
    restart: Backoff = Field(default_factory=Backoff)
    stop_timeout_s: float = Field(default=10.0, gt=0, description="SIGTERM, then SIGKILL after this")
    _source: Path = PrivateAttr(default=Path("<memory>"))

    @field_validator("robots")
    @classmethod
    def _robot_ids(cls, robots: list[str]) -> list[str]:
        from ovamos.shared.keys import check_chunk
        for robot in robots:
            check_chunk(robot, "robot id")
        if len(set(robots)) != len(robots):
            raise ValueError("a robot is named twice")
        return robots

    @property
    def source(self) -> Path:
        """The file it was loaded from (named in every error)."""
        return self._source

    def entries(self, router_connect: Sequence[str] | None = None,
                endpoint: str | None = None, *, certs: Path | None = None,
                listen_link: str | None = None, motion: DriveMode | None = None,
                changes: Mapping[str, dict[str, Any]] | None = None) -> list[Entry]:
        """The processes to supervise.

        ``router_connect`` replaces the router's connect endpoints (``--connect-laptop``
        on the robot); ``endpoint`` moves the router's plain TCP listener there and
        connects every service to it (tests and the demo use a free port rather than the
        shipped one); ``listen_link`` replaces its ``tls/`` listener, or adds one beside the loopback
        one (``--listen-link``).
        ``certs`` is the certificate folder of a router with a ``cert``. ``motion`` sets how the
        robot drives (:func:`motion_settings`); None: as the services' configs say. ``changes``: settings
        changed on top of a service's config (``ovamos run --set``, merged section by section), by
        entry name (``mapping-r2``) or else by service (``planner``): the demo's episode and ports.
        """
        changes = changes or {}
        found = [self._router_entry(router_connect, endpoint, certs, listen_link)] if self.router else []
        if not self.robots:
            return found + [self._service_entry(s, endpoint, motion=motion, changes=changes) for s in self.services]
        return found + self._fleet_entries(endpoint, motion, changes)

    def _fleet_entries(self, endpoint: str | None, motion: DriveMode | None,
                       changes: Mapping[str, dict[str, Any]]) -> list[Entry]:
        """A fleet's processes, in the profile's order: per-robot services once per robot."""
        from ovamos import fleet
        sim = next((s for s in self.services if s.service == "sim"), None)
        homes = fleet.scenes(service_config(sim), self.robots) if sim is not None else {}
        entries = []
        for spec in self.services:
            if spec.service in fleet.FLEET_WIDE:
                settings = fleet.fleet_wide_settings(spec.service, service_config(spec), self.robots, homes)
                entries.append(self._service_entry(spec, endpoint, settings=settings, motion=motion, changes=changes))
                continue
            entries += [self._service_entry(spec, endpoint, robot=robot, name=f"{spec.entry_name}-{robot}",
                                            settings=fleet.robot_settings(spec.service, homes.get(robot)),
                                            motion=motion, changes=changes)
                        for robot in self.robots]
        return entries

    def _router_entry(self, connect: Sequence[str] | None, endpoint: str | None, certs: Path | None,
                      listen_link: str | None) -> Entry:
        assert self.router is not None
        router = self.router
        listen = router.listen
        if endpoint or listen_link:
            base = listen or self.config_listen()
            plain = [e for e in base if not e.startswith("tls/")]
            link = [e for e in base if e.startswith("tls/")]
            listen = ([endpoint] if endpoint else plain) + ([listen_link] if listen_link else link)
        connect = list(connect) if connect is not None else router.connect
        argv = ["router", *_opt("--config", router.config), *_repeat("--listen", listen),
                *_repeat("--connect", connect)]
        if router.cert is not None:
            folder = (certs or DEFAULT_CERTS).resolve()
            argv += ["--certs", str(folder), "--cert", router.cert, "--robot-id", self.robot_id,
                     *_repeat("--robot", self.robots)]
        return Entry(router.name, tuple(argv), ready=self._router_address(listen))

    def config_listen(self) -> list[str]:
        return _flat_endpoints(self._router_config([]).get_json("listen/endpoints"))

    def _router_config(self, listen: list[str]) -> Any:
        from ovamos.shared.bus.zconfig import ZenohConfigError, build_config
        assert self.router is not None
        try:
            return build_config("router", file=self.router.config, listen=listen, require_certs=False)
        except ZenohConfigError as exc:
            raise ProfileError(f"{self.source}: router: {exc}") from None

    def _router_address(self, listen: list[str]) -> tuple[str, int]:
        """Where the router listens, from its config and overrides: what the services wait for."""
        for address in map(tcp_address, _flat_endpoints(self._router_config(listen).get_json("listen/endpoints"))):
            if address is not None:
                return address
        raise ProfileError(f"{self.source}: router: no tcp listen endpoint to wait for")

    @property
    def secure(self) -> bool:
        """Whether the router's links to other hosts are TLS (it has a certificate)."""
        return self.router is not None and self.router.cert is not None

    def _service_entry(self, spec: ServiceSpec, endpoint: str | None, *, robot: str | None = None,
                       name: str | None = None, settings: dict[str, Any] | None = None,
                       motion: DriveMode | None = None, changes: Mapping[str, dict[str, Any]] | None = None
                       ) -> Entry:
        if motion is not None:
            settings = {**(settings or {}), **motion_settings(spec.service, service_config(spec), motion)}
        entry = name or spec.entry_name
        changed = (changes or {}).get(entry, (changes or {}).get(spec.service))
        if changed:
            settings = merged(settings or {}, changed)
        argv = ["run", spec.service, "--robot-id", robot or spec.robot_id or self.robot_id,
                "--instance", spec.instance, *_opt("--config", spec.config), *_opt("--zenoh", spec.zenoh),
                *_repeat("--connect", [endpoint] if endpoint else spec.connect),
                *_repeat("--set", [format_override(k, v) for k, v in (settings or {}).items()])]
        return Entry(entry, tuple(argv), delay_s=spec.delay_s)


def motion_settings(service: str, config: Any, motion: DriveMode) -> dict[str, Any]:
    """The settings that make ``service`` (its ``config`` as loaded) take part in ``motion``: the
    planner drives that way (``[agent] motion``); the camera and the simulated robot take a frame
    after each command (stepwise) or free-run (continuous); a simulated robot on the kinematic base
    gets a wheeled one for continuous motion (paths are followed by a base controller)."""
    from ovamos.services.sim.wheels import CONTINUOUS_BASE  # (the simulator's modules: only when asked)
    lock_step = motion == "stepwise"
    if service == "planner":
        return {"agent": {**config.agent.model_dump(mode="json"), "motion": motion}}
    if service == "camera":
        return {"lock_step": lock_step}
    if service == "sim":
        wheels = CONTINUOUS_BASE if motion == "continuous" and config.motion == "kinematic" else config.motion
        return {"lock_step": lock_step, "motion": wheels}
    return {}


def service_config(spec: ServiceSpec) -> Any:
    """A service entry's config as its service's model (the fleet's settings are derived from it,
    ``ovamos doctor`` checks what it names)."""
    from ovamos.registry import service_class
    from ovamos.shared.service import load_config
    return load_config(service_class(spec.service), spec.config)


def _opt(flag: str, value: Path | None) -> list[str]:
    return [flag, str(value)] if value is not None else []


def _repeat(flag: str, values: Sequence[str]) -> list[str]:
    return [arg for value in values for arg in (flag, value)]


def _flat_endpoints(raw_json: str) -> list[str]:
    """Zenoh endpoints are a list, or per mode ``{"router": [...], ...}``."""
    value = json.loads(raw_json)
    if isinstance(value, dict):
        return [e for per_mode in value.values() for e in per_mode]
    return list(value or [])


def tcp_address(endpoint: str) -> tuple[str, int] | None:
    """(host, port) of a ``tcp/HOST:PORT`` endpoint to probe; a wildcard host is probed on loopback."""
    if not endpoint.startswith("tcp/"):
        return None
    host, _, port = endpoint[4:].split("#")[0].rpartition(":")
    if not port.isdigit() or not host:
        return None
    host = host.strip("[]")
    return ("127.0.0.1" if host in ("0.0.0.0", "::") else host), int(port)


def laptop_endpoint(address: str, protocol: str = "tcp", option: str = "--connect-laptop") -> str:
    """``HOST:PORT`` (from ``--connect-laptop``) as a Zenoh endpoint, or a clear error."""
    host, _, port = address.rpartition(":")
    if not host or not port.isdigit() or not 0 < int(port) < 65536:
        example = "7450" if protocol == "tls" else "7447"
        raise ProfileError(f"{option} wants HOST:PORT (e.g. 192.168.1.10:{example}), not {address!r}")
    return f"{protocol}/{host}:{port}"


def resolve_profile(name_or_path: str | Path) -> Path:
    """A profile file path, or a shipped profile's name (``all``, ``laptop``, ``robot``)."""
    path = Path(name_or_path)
    if path.suffix == ".toml" or path.exists():
        return path
    shipped = PROFILE_DIR / f"{name_or_path}.toml"
    if shipped.exists():
        return shipped
    raise ProfileError(f"unknown profile {str(name_or_path)!r}: give a .toml file or one of: "
                       f"{', '.join(shipped_profiles())}")


def load_profile(path: str | Path) -> Profile:
    """Read and fully check a profile; every problem is a :class:`ProfileError` naming file and entry.

    Relative paths in the file are taken from the file's folder (so ``ovamos up``
    works from any directory) and come back absolute.
    """
    path = Path(path)
    try:
        raw = tomllib.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise ProfileError(f"cannot read profile {path}: {exc}") from None
    try:
        profile = Profile.model_validate(raw)
    except ValidationError as exc:
        raise ProfileError(f"{path}: " + "; ".join(_describe(e, raw) for e in exc.errors())) from None
    profile._source = path
    _resolve_paths(profile, path.parent.resolve())
    _check(profile)
    return profile


def _describe(error: Any, raw: dict[str, Any]) -> str:
    """``services[2] (mapping): bogus: Extra inputs are not permitted`` from a pydantic error."""
    loc = list(error["loc"])
    where = ""
    if len(loc) >= 2 and loc[0] == "services" and isinstance(loc[1], int):
        item = raw.get("services", [])[loc[1]]
        label = item.get("name") or item.get("service") if isinstance(item, dict) else None
        where = f"services[{loc[1]}]" + (f" ({label})" if label else "")
        loc = loc[2:]
    field_path = ".".join(map(str, loc))
    return ": ".join(p for p in (where, field_path, error["msg"]) if p)


def _resolve_paths(profile: Profile, base: Path) -> None:
    def absolute(p: Path | None) -> Path | None:
        return p if p is None or p.is_absolute() else (base / p).resolve()
    if profile.router is not None:
        profile.router.config = absolute(profile.router.config)
    for spec in profile.services:
        spec.config, spec.zenoh = absolute(spec.config), absolute(spec.zenoh)


def _check(profile: Profile) -> None:
    """Unknown services, missing files and duplicate names, each reported with its entry."""
    problems: list[str] = []
    router = profile.router
    if router is not None and router.config is not None and not router.config.is_file():
        problems.append(f"router: config file {router.config} does not exist")
    names = [router.name] if router is not None else []
    for i, spec in enumerate(profile.services):
        problems += _service_problems(f"services[{i}] ({spec.entry_name})", spec, names)
        names.append(spec.entry_name)
    if not names:
        problems.append("no router and no services: nothing to run")
    if problems:
        raise ProfileError(f"{profile.source}: " + "; ".join(problems))


def _service_problems(where: str, spec: ServiceSpec, taken: list[str]) -> list[str]:
    problems = []
    if spec.service not in SERVICES:
        problems.append(f"{where}: unknown service {spec.service!r}; "
                        f"known: {', '.join(sorted(SERVICES))}")
    for what, p in (("config", spec.config), ("zenoh", spec.zenoh)):
        if p is not None and not p.is_file():
            problems.append(f"{where}: {what} file {p} does not exist")
    if spec.entry_name in taken:
        problems.append(f"{where}: name {spec.entry_name!r} is used twice (set a unique name)")
    return problems


def check_service_configs(profile: Profile) -> None:
    """Validate each service's config file against its service's model, before anything starts.

    This imports each named service (lazily, see :mod:`ovamos.registry`), so it
    is a separate step from :func:`load_profile`.
    """
    from ovamos.registry import UnknownServiceError, service_class
    from ovamos.shared.service import ServiceConfigError, load_config
    problems: list[str] = []
    for i, spec in enumerate(profile.services):
        try:
            load_config(service_class(spec.service), spec.config)
        except (UnknownServiceError, ServiceConfigError) as exc:
            problems.append(f"services[{i}] ({spec.entry_name}): {exc}")
    if problems:
        raise ProfileError(f"{profile.source}: " + "; ".join(problems))


def check_certs(profile: Profile, certs: Path | None) -> None:
    """A secure profile's certificate folder has the CA and this host's pair, valid now."""
    if not profile.secure:
        return
    from ovamos.shared.bus.zconfig import TlsFiles
    from ovamos.shared.certs import CertError, check_certificate, check_key
    assert profile.router is not None and profile.router.cert is not None
    files = TlsFiles.from_folder(certs or DEFAULT_CERTS, profile.router.cert)
    try:
        check_certificate(files.ca)
        check_certificate(files.cert)
        check_key(files.key)
    except CertError as exc:
        raise ProfileError(f"{profile.source}: router: {exc} (--certs names the folder)") from None


def supervisor_for(profile: str | Path, *, log_dir: Path = DEFAULT_LOG_DIR,
                   connect_laptop: str | None = None, endpoint: str | None = None,
                   check_configs: bool = True, certs: Path | None = None,
                   listen_link: str | None = None, motion: DriveMode | None = None) -> Supervisor:
    """What ``ovamos up PROFILE`` runs: the profile loaded, checked and turned into a supervisor.

    ``endpoint`` runs the profile's router there instead of its shipped port (see
    :meth:`Profile.entries`). ``listen_link``: where the router also listens for the other host
    (the laptop's address on the robot network), beside its loopback listener for its services. A
    secure profile (its router has a ``cert``) links over TLS: ``connect_laptop`` and
    ``listen_link`` are then ``tls/`` endpoints, and the certificates in ``certs`` are checked
    before anything starts. ``motion`` (``ovamos up --motion``): see
    :func:`motion_settings`.
    """
    loaded = load_profile(resolve_profile(profile))
    if check_configs:
        check_service_configs(loaded)
    check_certs(loaded, certs)
    protocol = "tls" if loaded.secure else "tcp"
    connect = [laptop_endpoint(connect_laptop, protocol)] if connect_laptop else None
    link = laptop_endpoint(listen_link, protocol, "--listen-link") if listen_link else None
    return Supervisor(loaded.entries(router_connect=connect, endpoint=endpoint, certs=certs, listen_link=link,
                                     motion=motion),
                      log_dir=log_dir, backoff=loaded.restart, stop_timeout_s=loaded.stop_timeout_s)
