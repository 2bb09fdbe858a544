"""The code version a benchmark episode records: a real git checkout, clean and dirty, and none."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest

from ovamos import __version__
from ovamos.bench.provenance import code_version


def git(root: Path, *args: str) -> str:
    return subprocess.run(["git", "-C", str(root), *args], capture_output=True, text=True, check=True).stdout.strip()


@pytest.mark.skipif(shutil.which("git") is None, reason="git is not installed")
def test_a_checkout_is_named_by_its_commit_and_marked_dirty_with_changes(tmp_path: Path) -> None:
    git(tmp_path, "init", "-q")
    (tmp_path / "a.py").write_text("x = 1\n")
    git(tmp_path, "add", "a.py")
    git(tmp_path, "-c", "user.name=t", "-c", "user.email=t@example.invalid", "commit", "-qm", "a")
    commit = git(tmp_path, "rev-parse", "--short=12", "HEAD")
    assert code_version(tmp_path) == commit
    (tmp_path / "a.py").write_text("x = 2\n")
    dirty = code_version(tmp_path)
    assert dirty.startswith(f"{commit}-dirty-")
    (tmp_path / "a.py").write_text("x = 3\n")
    assert code_version(tmp_path) not in (dirty, commit)  # other changes, another name


def test_a_copy_without_git_is_named_by_the_package_version_and_its_sources(tmp_path: Path) -> None:
    (tmp_path / "bench").mkdir()
    (tmp_path / "bench" / "a.py").write_text("x = 1\n")
    (tmp_path / "tests").mkdir()
    first = code_version(tmp_path)
    assert first.startswith(f"ovamos {__version__}+")
    (tmp_path / "tests" / "test_a.py").write_text("assert True\n")
    assert code_version(tmp_path) == first  # a test is not code a benchmark runs
    (tmp_path / "bench" / "a.py").write_text("x = 2\n")
    assert code_version(tmp_path) != first
