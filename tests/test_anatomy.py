"""Every service has the same anatomy, derived from its one declaration in the topology: an adapter
(``services/<x>/service.py``, a :class:`Service` named as its entry) whose config class lives in
``services/<x>/config.py``; the registry ``ovamos run`` uses is that table."""

from __future__ import annotations

import importlib

import pytest

from ovamos.registry import SERVICES, UnknownServiceError, service_class
from ovamos.shared.service import Service
from ovamos.shared.topology import TOPOLOGY


@pytest.mark.parametrize("name", sorted(TOPOLOGY))
def test_each_declared_service_is_an_adapter_named_as_declared_with_its_config_in_config_py(name: str) -> None:
    module, _, attr = TOPOLOGY[name].adapter.partition(":")
    package = module.rsplit(".", 1)[0]
    assert module == f"{package}.service", f"{name}: the adapter is not a service.py"
    cls = service_class(name)
    assert issubclass(cls, Service) and cls.name == name and cls is getattr(importlib.import_module(module), attr)
    assert cls.Config.__module__ == f"{package}.config", f"{name}: {cls.Config.__name__} is in {cls.Config.__module__}"


def test_the_registry_is_the_topology_and_an_unknown_name_lists_the_known() -> None:
    assert list(SERVICES) == list(TOPOLOGY)
    with pytest.raises(UnknownServiceError, match="unknown service 'nope'; available: sim, base_driver"):
        service_class("nope")


def test_the_robots_path_loads_no_benchmark_and_no_heavy_library() -> None:
    """``ovamos run base_driver`` on a robot: the command line and the driver's adapter load only the
    benchmark's policy table (the CLI's help lists it) and none of torch, MuJoCo, scikit-learn,
    OpenCV or rclpy."""
    import json
    import subprocess
    import sys
    probe = ("import json, sys, ovamos.cli, ovamos.services.base_driver.service; "
             "print(json.dumps(sorted(m for m in sys.modules if m.startswith('ovamos.bench.') "
             "or m.split('.')[0] in ('torch', 'mujoco', 'sklearn', 'cv2', 'rclpy'))))")
    done = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout) == ["ovamos.bench.policies"]
