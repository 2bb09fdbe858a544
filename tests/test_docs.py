"""The documentation: generated references that match the code, a site that builds, links that resolve.

* ``docs/reference/*.md`` are what ``tools/gen_reference.py`` makes from the code now: a config
  field, a description or a key changed without regenerating fails here (``make docs`` regenerates).
* ``mkdocs build --strict`` succeeds (a broken link or anchor in a page is a warning, so a failure).
* The README stays an entry point (under ``README_MAX_LINES``), and every relative link in it and
  in ``docs/`` points at a file that exists (and, within the README, at a heading it has).
"""

from __future__ import annotations

import importlib.util
import os
import re
import subprocess
import sys
from pathlib import Path
from types import ModuleType

import pytest
from pydantic import BaseModel, Field

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
README_MAX_LINES = 200


def _load_generator() -> ModuleType:
    spec = importlib.util.spec_from_file_location("gen_reference", ROOT / "tools" / "gen_reference.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


gen = _load_generator()


# -- generated references ---------------------------------------------------------------------------
@pytest.fixture(scope="module")
def rendered() -> dict[Path, str]:
    return gen.render()


def test_generated_references_match_the_code(rendered: dict[Path, str]) -> None:
    stale = gen.stale(rendered, ROOT)
    assert not stale, f"stale generated docs: {[str(p) for p in stale]}; run: python tools/gen_reference.py"


def test_generation_is_deterministic(rendered: dict[Path, str]) -> None:
    assert gen.render() == rendered


def test_every_service_and_its_settings_are_in_the_config_reference(rendered: dict[Path, str]) -> None:
    from ovamos.registry import SERVICES, service_class

    text = rendered[gen.REFERENCE_DIR / "config.md"]
    for name in SERVICES:
        assert f"\n## {name}\n" in text
        for field in service_class(name).Config.model_fields:
            assert f"| `{field}` |" in text, f"{name}.{field} missing"


def test_every_key_of_the_topology_is_in_its_reference(rendered: dict[Path, str]) -> None:
    from ovamos.shared.topology import TOPOLOGY

    text = rendered[gen.REFERENCE_DIR / "topology.md"]
    for name, node in TOPOLOGY.items():
        assert f"\n### {name}\n" in text
        for port in (*node.inputs, *node.outputs, *node.answers, *node.queries):
            assert f"`{port.key('{robot_id}')}`" in text


class _Inner(BaseModel):
    rate_hz: float = Field(default=5.0, gt=0, description="how often | and *why*")


class _Demo(BaseModel):
    mode: str = Field(default="a", description="the mode")
    inner: _Inner = Field(default_factory=_Inner)
    maybe: _Inner | None = None


def test_the_architecture_page_names_every_import_contract_and_service() -> None:
    """docs/architecture.md is the map of the layers: each contract `make lint` runs is listed there
    by its name, and each service of the topology is named."""
    import tomllib

    from ovamos.shared.topology import TOPOLOGY
    page = (DOCS / "architecture.md").read_text()
    contracts = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["importlinter"]["contracts"]
    assert [c["name"] for c in contracts if f"- {c['name']}\n" not in page] == []
    listed = re.findall(r"^- (.+)$", page.split("as `make lint` names them")[1].split("## ")[0], re.M)
    assert sorted(listed) == sorted(c["name"] for c in contracts)  # none listed that is not run
    services = (DOCS / "services.md").read_text()
    assert [s for s in TOPOLOGY if f"| `{s}` |" not in services] == []


def test_a_changed_field_changes_the_config_reference(tmp_path: Path) -> None:
    before = gen.config_reference({"demo": _Demo}, root=tmp_path)
    assert "| `inner.rate_hz` | `float`, > 0 | `5.0` | how often \\| and \\*why\\* |" in before
    assert "| `maybe.rate_hz` |" in before and "| `maybe` | `_Inner` \\| `None` | `null` |" in before

    class _Changed(_Demo):
        mode: str = Field(default="b", description="the mode")

    after = gen.config_reference({"demo": _Changed}, root=tmp_path)
    assert after != before and "| `mode` | `str` | `\"b\"` | the mode |" in after


def test_check_names_stale_and_missing_files(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert gen.main(["--root", str(tmp_path)]) == 0            # writes both
    assert gen.main(["--check", "--root", str(tmp_path)]) == 0
    config = tmp_path / gen.REFERENCE_DIR / "config.md"
    config.write_text(config.read_text() + "edited by hand\n")
    (tmp_path / gen.REFERENCE_DIR / "topology.md").unlink()
    capsys.readouterr()
    assert gen.main(["--check", "--root", str(tmp_path)]) == 1
    err = capsys.readouterr().err
    assert "config.md" in err and "topology.md" in err


# -- the site ---------------------------------------------------------------------------------------
def test_the_site_builds_strict(tmp_path: Path) -> None:
    if importlib.util.find_spec("mkdocs") is None or importlib.util.find_spec("material") is None:
        pytest.skip("mkdocs-material is not installed (pip install -e '.[docs]')")
    env = {**os.environ, "NO_MKDOCS_2_WARNING": "1"}
    proc = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "--config-file",
                           str(ROOT / "mkdocs.yml"), "--site-dir", str(tmp_path / "site")],
                          cwd=ROOT, capture_output=True, text=True, timeout=170, env=env)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert (tmp_path / "site" / "index.html").is_file()
    assert (tmp_path / "site" / "reference" / "config.html").is_file()


# -- README and links -------------------------------------------------------------------------------
_FENCE = re.compile(r"^(```|~~~).*?^\1", re.S | re.M)
_CODE = re.compile(r"`[^`\n]*`")
_LINK = re.compile(r"!?\[[^\]\n]*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
_REF = re.compile(r"^\s*\[[^\]\n]+\]:\s*<?(\S+?)>?(?:\s+\".*\")?\s*$", re.M)


def links(markdown: str) -> list[str]:
    """The link targets of a Markdown text, code blocks and code spans left out."""
    text = _CODE.sub("", _FENCE.sub("", markdown))
    return _LINK.findall(text) + _REF.findall(text)


def github_anchor(heading: str) -> str:
    text = _CODE.sub(lambda m: m.group(0)[1:-1], heading.strip()).lower()
    return re.sub(r"[^\w\- ]", "", text).replace(" ", "-")


def anchors_of(path: Path) -> set[str]:
    text = path.read_text(encoding="utf-8")
    return {github_anchor(h) for h in re.findall(r"^#{1,6} (.+?)\s*#*$", _FENCE.sub("", text), re.M)}


def broken_links(path: Path) -> list[str]:
    """The relative links of one Markdown file that point at no file, or at a heading that the
    Markdown file they name (this one, for ``#anchor``) does not have."""
    bad = []
    for target in links(path.read_text(encoding="utf-8")):
        if re.match(r"^[a-z][a-z0-9+.-]*:", target, re.I) or target.startswith("//"):
            continue  # http:, https:, mailto: ...
        file, _, anchor = target.partition("#")
        linked = path.parent / file if file else path
        if not linked.exists():
            bad.append(target)
        elif anchor and linked.suffix == ".md" and anchor not in anchors_of(linked):
            bad.append(target)
    return bad


def test_the_link_checker_finds_broken_links(tmp_path: Path) -> None:
    (tmp_path / "there.md").write_text("# There\n\n## `ovamos run` (one service)\n")
    page = tmp_path / "page.md"
    page.write_text("# A heading\n\n[ok](there.md) [ok too](#a-heading) [web](https://example.org/x)\n"
                    "[ok](there.md#ovamos-run-one-service) [not there](there.md#nope)\n"
                    "[gone](missing.md) ![gone too](img/none.png) [no such heading](#nowhere)\n"
                    "`[not a link](missing-in-code.md)`\n\n```\n[nor this](missing-in-block.md)\n```\n"
                    "[ref]: also-missing.md\n")
    assert sorted(broken_links(page)) == ["#nowhere", "also-missing.md", "img/none.png", "missing.md",
                                          "there.md#nope"]


def test_readme_is_short() -> None:
    lines = (ROOT / "README.md").read_text(encoding="utf-8").count("\n")
    assert lines < README_MAX_LINES, f"README.md has {lines} lines; move detail into docs/"


@pytest.mark.parametrize("path", [ROOT / "README.md", ROOT / "CHANGELOG.md", *sorted(DOCS.rglob("*.md"))],
                         ids=lambda p: str(p.relative_to(ROOT)))
def test_relative_links_resolve(path: Path) -> None:
    assert broken_links(path) == [], f"{path.relative_to(ROOT)}: links to nothing"
