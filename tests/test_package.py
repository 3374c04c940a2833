"""Meta-tests that keep the package surface honest."""

from __future__ import annotations

import importlib
import subprocess
import sys
from pathlib import Path

import pytest

import gateway

ROOT = Path(__file__).resolve().parents[1]
MODULES = sorted(
    ".".join(path.relative_to(ROOT).with_suffix("").parts)
    for package in ("gateway", "sinks", "sources", "processors", "tracking")
    for path in (ROOT / package).rglob("*.py")
    if path.name not in ("__init__.py", "__main__.py")
)


def test_all_is_sorted_and_exactly_the_public_names() -> None:
    public = {name for name in dir(gateway) if not name.startswith("_")}
    helpers = {"annotations", "importlib", "TYPE_CHECKING", "Any"}
    submodules = {name for name in public if type(getattr(gateway, name)).__name__ == "module"}
    assert gateway.__all__ == sorted(gateway.__all__)
    assert set(gateway.__all__) == public - submodules - helpers
    for name in gateway.__all__:
        home = importlib.import_module(gateway._HOME[name])
        assert getattr(gateway, name) is getattr(home, name)


@pytest.mark.slow
def test_every_module_imports_on_its_own() -> None:
    """Each module imported alone in a fresh interpreter: no hidden import-order cycles.

    Slow (every module of the project imported afresh, ~200 times): CI runs it, the quick
    loop does not.
    """
    code = (
        "import importlib, sys\n"
        "for name in sys.argv[1:]:\n"
        "    ours = ('gateway', 'sinks', 'sources', 'processors', 'tracking')\n"
        "    for loaded in [m for m in sys.modules if m.startswith(ours)]:\n"
        "        del sys.modules[loaded]\n"
        "    importlib.import_module(name)\n"
    )
    result = subprocess.run(
        [sys.executable, "-c", code, *MODULES], capture_output=True, text=True, check=False
    )
    assert result.returncode == 0, result.stderr


@pytest.mark.parametrize("module", MODULES)
def test_every_module_declares_all(module: str) -> None:
    path = ROOT / Path(*module.split(".")).with_suffix(".py")
    assert "__all__ = [" in path.read_text(), f"{module} has no __all__"
