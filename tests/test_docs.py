"""The documentation a newcomer and an operator read stays inside the repo and true."""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

from gateway.ops.share import DESCRIPTIONS

ROOT = Path(__file__).resolve().parents[1]
DOCS = [ROOT / "README.md", ROOT / "deploy" / "INSTALL.md", *sorted((ROOT / "docs").glob("*.md"))]
LINK = re.compile(r"\]\(([^)#\s]+)(?:#[^)]*)?\)")


@pytest.mark.parametrize("doc", DOCS, ids=lambda p: str(p.relative_to(ROOT)))
def test_relative_links_resolve_inside_the_repository(doc: Path) -> None:
    for target in LINK.findall(doc.read_text()):
        if re.match(r"[a-z]+:", target):
            continue  # http(s):, file:, mailto:
        resolved = (doc.parent / target).resolve()
        assert resolved.is_relative_to(ROOT), f"{doc.name} links outside the repo: {target}"
        assert resolved.exists(), f"{doc.name} links to a missing file: {target}"


def test_the_sink_guide_shows_the_example_sink_verbatim() -> None:
    guide = (ROOT / "docs" / "writing-a-sink.md").read_text()
    assert (ROOT / "sinks" / "example.py").read_text() in guide
    assert "## Changes in progress" in guide  # the section the contract rework updates


def test_install_names_the_debian_packages_and_the_terrain_extra() -> None:
    install = (ROOT / "deploy" / "INSTALL.md").read_text()
    assert "sudo apt-get install python3-venv proj-data" in install
    assert "[terrain]" in install
    assert "fischer-gateway files --out /opt/fischer-gateway/share" in install


def test_the_units_documentation_is_what_files_out_writes() -> None:
    unit = (ROOT / "deploy" / "fischer-gateway.service").read_text()
    (line,) = [x for x in unit.splitlines() if x.startswith("Documentation=")]
    uris = line.removeprefix("Documentation=").split()
    assert uris
    for uri in uris:
        path = Path(uri.removeprefix("file://"))
        assert path.parent == Path("/opt/fischer-gateway/share"), uri
        assert path.name in DESCRIPTIONS, uri


def test_the_wheel_ships_config_unit_docs_contract_and_example(tmp_path: Path) -> None:
    # Built from a copy: setuptools leaves build/ and egg-info in the tree it builds.
    tree = tmp_path / "tree"
    shutil.copytree(
        ROOT,
        tree,
        ignore=shutil.ignore_patterns(".*", "build", "*.egg-info", "__pycache__", "tests"),
    )
    subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", str(tmp_path), str(tree)],
        check=True,
        capture_output=True,
        timeout=120,
    )
    (wheel,) = tmp_path.glob("fischer_gateway-*.whl")
    with zipfile.ZipFile(wheel) as archive:
        names = set(archive.namelist())
        for name in DESCRIPTIONS:
            shipped = archive.read(f"gateway/data/share/{name}").decode()
            assert shipped, name  # a symlink would have been shipped as its target's text
        assert (
            archive.read("gateway/data/share/example.yaml").decode()
            == (ROOT / "config" / "example.yaml").read_text()
        )
    assert {"gateway/contract.py", "gateway/testing.py", "sinks/example.py"} <= names
    # The map page runs on what the wheel ships: no network beyond the node.
    assert {
        "sinks/map/static/index.html",
        "sinks/map/static/map.js",
        "sinks/map/static/vendor/leaflet/leaflet.js",
        "sinks/map/static/vendor/milsymbol/milsymbol.js",
        "sinks/map/static/vendor/topojson-client/topojson-client.min.js",
        "sinks/map/static/vendor/world-atlas/land-50m.json",
    } <= names
    # Each integration's schemas ship inside its own package.
    assert {
        "sinks/gute2/schemas/gute2-handoff.schema.json",
        "sinks/gute2/schemas/gute2-handoff-1.schema.json",
        "sinks/slb/schemas/slb-object-item.schema.json",
        "sinks/slb/schemas/slb-order.schema.json",
        "sinks/sweccis/schemas/sweccis-fas.xsd",
        "sinks/sweccis/schemas/sweccis-fas-2.xsd",
        "sinks/map/schemas/stream.schema.json",
    } <= names


def _anchors(markdown: str) -> set[str]:
    """The anchors a renderer gives the headings (GitHub's rule: lower case, punctuation
    dropped, spaces to hyphens)."""
    headings = re.findall(r"^#+ (.+)$", markdown, re.MULTILINE)
    return {re.sub(r"[^\w\- ]", "", h.strip().lower()).replace(" ", "-") for h in headings}


def test_what_files_out_ships_links_only_to_what_it_ships(tmp_path: Path) -> None:
    """An operator reading /opt/fischer-gateway/share follows every relative link there:
    each leads to a shipped file (and a heading of it, for an #anchor)."""
    from gateway.ops.share import write_shared

    written = {path.name: path for path in write_shared(tmp_path)}
    followed = 0
    for name, path in written.items():
        if not name.endswith(".md"):
            continue
        for target, anchor in re.findall(r"\]\(([^)#\s]*)(#[^)\s]*)?\)", path.read_text()):
            if re.match(r"[a-z][a-z0-9+.-]*:", target):
                continue  # the web
            landing = (tmp_path / target) if target else path
            assert landing.resolve().parent == tmp_path.resolve(), f"{name} leaves: {target}"
            assert landing.is_file(), f"{name} links to {target}, which is not shipped"
            if anchor:
                assert anchor[1:] in _anchors(landing.read_text()), f"{name}: {target}{anchor}"
            followed += 1
    assert followed > 50
