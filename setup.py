"""The one import root: the folders ``shared/``, ``services/``, ``world/``, ``bench/`` and ``deploy/``
stay at the top of the checkout and install as ``ovamos.shared``, ``ovamos.services``, ``ovamos.world``,
``ovamos.bench`` and ``ovamos.deploy``; everything else is in pyproject.toml. The package list is computed here because
pyproject's ``packages.find`` cannot put a prefix on the packages it finds."""

from setuptools import find_packages, setup

MAPPED = ("shared", "services", "world", "bench", "deploy")

packages = ["ovamos", *(f"ovamos.{p}" for p in find_packages(include=["record", "record.*"], where="ovamos"))]
for folder in MAPPED:
    packages += [f"ovamos.{folder}", *(f"ovamos.{folder}.{p}" for p in find_packages(where=folder))]

setup(packages=packages, package_dir={"ovamos": "ovamos", **{f"ovamos.{f}": f for f in MAPPED}})
