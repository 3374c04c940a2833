"""The layering of the packages is a checked contract, not a convention.

Every import between the project's modules (read from the source, ``TYPE_CHECKING`` imports
included) must run down the layers or stay inside one part of a layer. The sides of the bus
do not know each other: the airframe side (``gateway.fleet``), the middle
(``gateway.flow``) and the C2 side (``gateway.c2`` and the plugins in ``sinks``/``sources``)
meet only in ``gateway.app``. The core never imports a plugin: plugins are found through
entry points.

An import is any way a module names another: ``import a.b``, ``from a import b`` (which names
the module ``a.b`` when ``b`` is one: ``from gateway import app``), relative imports, and
``importlib.import_module("a.b")`` or ``__import__("a.b")`` with a literal name. The
``TestInjectedViolations`` prove each form is caught.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

#: The integrations, each a package under ``sinks`` that imports only the core (``c2``, the
#: public face and the layers below): never another integration.
INTEGRATIONS = ("cot", "gute2", "klv", "map", "nats", "nffi", "ra180", "slb", "sweccis")

#: (layer, part) for each module prefix; the longest matching prefix wins.
LAYERS: dict[str, tuple[int, str]] = {
    "gateway.errors": (0, "base"),
    "gateway.events": (0, "base"),
    "gateway.clock": (0, "base"),
    "gateway.ops.logsetup": (0, "base"),
    "gateway.ops.metrics": (0, "base"),
    "gateway.ops.version": (0, "base"),
    "gateway.domain": (1, "domain"),
    "gateway.config": (2, "config"),
    "gateway.configfile": (2, "config"),
    "gateway.transports": (2, "transports"),
    "gateway.ops": (2, "ops"),
    "gateway.spool": (2, "spool"),
    "gateway.fleet": (3, "fleet"),
    "gateway.sim": (3, "sim"),
    "gateway.flow": (3, "flow"),
    "gateway.c2": (3, "c2"),
    "gateway.testing": (3, "c2"),
    # The plugin contracts and their checkers: names the sink, source and processor sides.
    "gateway.contract": (3, "contract"),
    # The generic sinks (console, jsonl, the example) and the local order source...
    "sinks": (3, "sinks"),
    "sources": (3, "sources"),
    # ...and one package per integration: codec, link, sink and source together.
    **{f"sinks.{name}": (3, name) for name in INTEGRATIONS},
    "processors": (3, "processors"),
    "tracking": (3, "tracking"),
    "gateway.app": (4, "assembly"),
    "gateway.configcheck": (4, "assembly"),
    "gateway.configschema": (4, "assembly"),
    "gateway.reload": (4, "assembly"),
    "gateway.demo": (4, "assembly"),
    "gateway.scoring": (4, "scoring"),
    "gateway.cli": (5, "entry"),
    "gateway.ordercli": (5, "entry"),
    "gateway.__main__": (5, "entry"),
    # ``python -m gateway.events_doc``: writes docs/events.md from the event models.
    "gateway.events_doc": (5, "entry"),
    # The package's public face (``from gateway import Sink``): for plugin authors. It only
    # re-exports lazily, so its own imports (under TYPE_CHECKING) are not checked.
    "gateway": (3, "public"),
}

#: Parts of one layer that may import each other, in this direction only.
ALLOWED_ACROSS: set[tuple[str, str]] = {
    ("ops", "transports"),
    ("ops", "config"),
    ("sim", "fleet"),
    # The simulator plays ATAK's SA mesh with the CoT integration's codec.
    ("sim", "cot"),
    ("sinks", "c2"),
    ("sources", "c2"),
    ("sinks", "public"),
    ("sources", "public"),
    # The local order source reads the order document the SLB integration defines.
    ("sources", "slb"),
    *((name, side) for name in INTEGRATIONS for side in ("c2", "public")),
    ("processors", "flow"),
    ("processors", "tracking"),
    ("tracking", "flow"),
    ("processors", "public"),
    ("contract", "c2"),
    ("contract", "flow"),
}

#: Calls that import the module their first argument names.
IMPORT_CALLS = {"import_module", "__import__"}


def _layer(module: str) -> tuple[int, str] | None:
    if module == "gateway":
        return LAYERS["gateway"]  # the public face matches exactly, never as a prefix
    best = None
    for prefix, layer in LAYERS.items():
        if prefix == "gateway":
            continue
        if (module == prefix or module.startswith(prefix + ".")) and (
            best is None or len(prefix) > len(best[0])
        ):
            best = (prefix, layer)
    return None if best is None else best[1]


def _modules() -> dict[str, Path]:
    found = {}
    for package in ("gateway", "sinks", "sources", "processors", "tracking"):
        for path in (ROOT / package).rglob("*.py"):
            parts = list(path.relative_to(ROOT).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            found[".".join(parts)] = path
    return found


def _imports(module: str, path: Path, known: frozenset[str] | None = None) -> set[str]:
    """Every project module ``module`` (at ``path``) names; ``known``: the project's modules."""
    known = frozenset(_modules()) if known is None else known
    names = set()
    package = module.split(".") if path.name == "__init__.py" else module.split(".")[:-1]
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom):
            if node.level > 0:
                # Relative imports count too: ``from ..c2 import x`` is gateway.c2.x.
                base = package[: len(package) - node.level + 1]
                source = ".".join([*base, *(node.module.split(".") if node.module else [])])
            else:
                source = node.module or ""
            names.add(source)
            # ``from gateway import app`` imports the module gateway.app, not a name of gateway.
            names.update(
                f"{source}.{alias.name}"
                for alias in node.names
                if f"{source}.{alias.name}" in known
            )
        elif isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif (
            isinstance(node, ast.Call)
            and _called_name(node.func) in IMPORT_CALLS
            and node.args
            and isinstance(node.args[0], ast.Constant)
            and isinstance(node.args[0].value, str)
        ):
            names.add(node.args[0].value)
    return {
        n
        for n in names
        if n.split(".")[0] in ("gateway", "sinks", "sources", "processors", "tracking")
    }


def _called_name(func: ast.expr) -> str | None:
    if isinstance(func, ast.Name):
        return func.id
    if isinstance(func, ast.Attribute):
        return func.attr
    return None


def _violations(module: str, path: Path, known: frozenset[str] | None = None) -> list[str]:
    """How ``module``'s imports break the layering (empty when they do not)."""
    here = _layer(module)
    assert here is not None
    if module == "gateway":
        return []
    broken = []
    for imported in sorted(_imports(module, path, known)):
        there = _layer(imported)
        if there is None or imported == module:
            continue
        if there[0] > here[0]:
            broken.append(f"{module} -> {imported}: runs up from layer {here[0]} to {there[0]}")
        elif (
            there[0] == here[0]
            and there[1] != here[1]
            and (here[1], there[1]) not in ALLOWED_ACROSS
        ):
            broken.append(f"{module} -> {imported}: {here[1]} may not import {there[1]}")
    return broken


def test_every_module_has_a_layer() -> None:
    assert [m for m in _modules() if _layer(m) is None] == []


def test_imports_run_down_the_layers_and_the_sides_stay_apart() -> None:
    known = frozenset(_modules())
    broken = [
        problem
        for module, path in sorted(_modules().items())
        for problem in _violations(module, path, known)
    ]
    assert broken == []


#: Core modules that may name a plugin, and why.
PLAYS_A_PEER = {
    # The simulator plays ATAK's SA mesh: it writes CoT with the CoT integration's codec.
    "gateway.sim.runner": {"sinks.cot.codec", "sinks.cot.event", "sinks.cot.validate"},
    # The scorer listens as the Ra 180 net: it reads the CDMs the radio heard.
    "gateway.scoring.announce": {"sinks.ra180.cdm"},
}


def test_the_core_never_imports_a_plugin() -> None:
    known = frozenset(_modules())
    offenders = [
        f"{module} -> {imported}"
        for module, path in _modules().items()
        if module.split(".")[0] == "gateway"
        for imported in _imports(module, path, known)
        if imported.split(".")[0] in ("sinks", "sources", "processors")
        and imported not in PLAYS_A_PEER.get(module, set())
    ]
    assert offenders == []


def test_each_integration_is_one_package_that_imports_only_the_core() -> None:
    """Changing one integration touches one package: no integration imports another, and
    nothing outside an integration names its modules (but the peers the simulator plays and
    the order document the local source reads)."""
    known = frozenset(_modules())
    allowed = {("sources.local", "sinks.slb.order")} | {
        (module, imported) for module, names in PLAYS_A_PEER.items() for imported in names
    }
    crossing = []
    for module, path in sorted(_modules().items()):
        mine = module.split(".")[1] if module.startswith("sinks.") else None
        for imported in sorted(_imports(module, path, known)):
            parts = imported.split(".")
            if parts[0] != "sinks" or len(parts) < 2 or parts[1] not in INTEGRATIONS:
                continue
            if (
                parts[1] != (mine if mine in INTEGRATIONS else None)
                and (
                    module,
                    imported,
                )
                not in allowed
            ):
                crossing.append(f"{module} -> {imported}")
    assert crossing == []
    for name in INTEGRATIONS:  # each is a package with a face
        assert (ROOT / "sinks" / name / "__init__.py").is_file(), name


class TestInjectedViolations:
    """Each way of importing across the layers, written into a module, is caught."""

    @pytest.mark.parametrize(
        ("module", "source", "expected"),
        [
            ("sinks.injected", "import gateway.app\n", "sinks.injected -> gateway.app"),
            ("sinks.injected", "from gateway import app\n", "sinks.injected -> gateway.app"),
            ("sinks.injected", "from gateway.fleet import session\n", "sinks may not import fleet"),
            (
                "processors.injected",
                "from gateway import fleet\n",
                "processors.injected -> gateway.fleet: processors may not import fleet",
            ),
            (
                "gateway.flow.injected",
                "from .. import app\n",
                "gateway.flow.injected -> gateway.app",
            ),
            (
                "sources.injected",
                "import importlib\nimportlib.import_module('gateway.fleet.ingest')\n",
                "sources may not import fleet",
            ),
            (
                "sources.injected",
                "from importlib import import_module\nimport_module('gateway.app')\n",
                "sources.injected -> gateway.app",
            ),
            ("sinks.injected", "__import__('gateway.cli')\n", "sinks.injected -> gateway.cli"),
            ("gateway.errors", "from gateway.fleet import session\n", "runs up from layer 0"),
            ("sinks.nffi.injected", "from sinks.cot import codec\n", "nffi may not import cot"),
        ],
    )
    def test_is_caught(self, module: str, source: str, expected: str, tmp_path: Path) -> None:
        path = tmp_path / "injected.py"
        path.write_text(source)
        problems = _violations(module, path, frozenset(_modules()))
        assert any(expected in p for p in problems), problems

    def test_public_names_and_allowed_imports_stay_allowed(self, tmp_path: Path) -> None:
        path = tmp_path / "injected.py"
        path.write_text(
            "from gateway import Sink, SinkConfig\nfrom gateway.c2.sink import Sink\n"
            "import importlib\nimportlib.import_module(name)\n"
        )
        assert _violations("sinks.injected", path, frozenset(_modules())) == []

    def test_the_core_importing_a_plugin_by_name_is_seen(self, tmp_path: Path) -> None:
        path = tmp_path / "injected.py"
        path.write_text("import importlib\nimportlib.import_module('sinks.cot.sink')\n")
        assert "sinks.cot.sink" in _imports("gateway.app", path, frozenset(_modules()))


def test_the_import_graph_in_the_architecture_page_is_the_codes() -> None:
    import import_graph

    page = import_graph.DOC.read_text(encoding="utf-8")
    assert import_graph.START in page
    assert import_graph.END in page
    expected = import_graph.page_with(page, import_graph.section())
    assert page == expected, "run: python tests/import_graph.py --write"


#: Test directories that are not a package's mirror: runs of the whole daemon, and the
#: stand-in plugins and type checks of the plugin face.
CROSS_CUTTING = ("e2e", "attack", "faults", "plugins", "typing")


def test_the_tests_mirror_the_packages() -> None:
    """A test directory is named after the package it tests (``tests/gateway/fleet`` tests
    ``gateway/fleet``), so whoever changes a package finds its tests at the same path."""
    tests = ROOT / "tests"
    strays = []
    for directory in sorted(tests.rglob("*")):
        if not directory.is_dir() or directory.name.startswith((".", "__")):
            continue
        relative = directory.relative_to(tests)
        if relative.parts[0] in CROSS_CUTTING or "fake_plugins" in relative.parts:
            continue
        if not any(directory.glob("test_*.py")):
            continue
        if not (ROOT / relative / "__init__.py").is_file():
            strays.append(str(relative))
    assert strays == [], f"test directories with no package of that path: {strays}"
    loose = sorted(p.name for p in (tests / "gateway").glob("test_*.py"))
    top = {p.stem for p in (ROOT / "gateway").glob("*.py")}
    assert [n for n in loose if not any(n.startswith(f"test_{m}") for m in top)] == []
