"""The layers hold: no import points upward, no import cycle, the engine never imports the app.

The rules and the parser are in ``scripts/layers.py`` (docs/ARCHITECTURE.md draws them).
"""

from __future__ import annotations

import importlib.util
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _layers():
    spec = importlib.util.spec_from_file_location("layers", ROOT / "scripts" / "layers.py")
    assert spec and spec.loader
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_no_upward_import() -> None:
    layers = _layers()
    assert layers.upward_imports(layers.graph()) == []


def test_no_import_cycle() -> None:
    layers = _layers()
    assert layers.cycles(layers.graph()) == []


def test_adapters_share_code_only_through_the_engine() -> None:
    # The command line imports nothing of the web app but its entry point; the web app nothing of the command line.
    layers = _layers()
    assert layers.adapter_crossings(layers.graph()) == []
    g = {"app.cli.x": {"app.web.panels": 4, "app.web.main": 5}, "app.web.y": {"app.cli": 2}}
    assert len(layers.adapter_crossings(g)) == 2  # the check can fail: the panel and the CLI edge, not main


def test_engine_never_imports_the_app() -> None:
    layers = _layers()
    g = layers.graph()
    bad = [(m, t) for m, targets in g.items() if m.startswith("registration") for t in targets if t.startswith("app")]
    assert bad == []


def test_the_checker_sees_violations() -> None:
    # The check must be able to fail: an upward edge and a two-module cycle are reported.
    layers = _layers()
    g = {"registration.core.x": {"registration.sim.y": 3}, "registration.sim.y": {"registration.core.x": 1}}
    assert len(layers.upward_imports(g)) == 1
    assert layers.cycles(g) == [["registration.core.x", "registration.sim.y"]]
    assert len(layers.graph()) > 30  # it parsed the real tree
