"""The layers of the project, and a check that imports respect them.

Run ``python scripts/layers.py`` to print the import graph's violations (none on a healthy
tree); ``tests/test_architecture.py`` runs the same check. Every ``import`` counts, at module
level or inside a function, under ``TYPE_CHECKING`` or not: a lazy import is still a
dependency.

Layers, lowest first. A module may import modules of its own layer and of layers below it,
never above; and no chain of imports may lead from a module back to itself. The two adapters,
``app.cli`` and ``app.web``, share code only through the engine: the command line imports the web
app's entry point (to start it) and nothing else of it.
"""

from __future__ import annotations

import ast
import sys
from collections.abc import Iterator
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

#: (layer name, package prefixes it holds), lowest first.
LAYERS: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("version", ("registration",)),  # only the package's __init__: the version string
    ("core", ("registration.core",)),
    ("io", ("registration.io",)),
    ("sim", ("registration.sim",)),
    ("studies", ("registration.studies",)),
    ("api", ("registration.api",)),  # the public face; registration/__init__ reaches it by name, lazily
    ("web", ("app.web",)),  # the web app: never imports the command line
    ("cli", ("app", "app.cli")),  # the command line: the engine's commands, and it starts the web app
)
PACKAGES = ("registration", "app")
#: The only web-app modules the command line may import: the app's entry point, which it starts.
CLI_REACHES_WEB = ("app.web.main",)


def module_name(path: Path) -> str:
    rel = path.relative_to(ROOT).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def modules() -> dict[str, Path]:
    out = {}
    for pkg in PACKAGES:
        for path in sorted((ROOT / pkg).rglob("*.py")):
            out[module_name(path)] = path
    return out


def layer_of(module: str) -> int:
    best, best_len = -1, -1
    for rank, (_name, prefixes) in enumerate(LAYERS):
        for prefix in prefixes:
            if (module == prefix or module.startswith(prefix + ".")) and len(prefix) > best_len:
                best, best_len = rank, len(prefix)
    if best < 0:
        raise ValueError(f"{module} belongs to no layer")
    return best


def imports_of(module: str, path: Path, known: dict[str, Path]) -> Iterator[tuple[str, int]]:
    """Project modules imported by ``module`` (the deepest known module of each name), with line."""
    tree = ast.parse(path.read_text(), filename=str(path))
    is_pkg = path.name == "__init__.py"
    for node in ast.walk(tree):
        names: list[str] = []
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = module.split(".")
                anchor = anchor if is_pkg else anchor[:-1]
                anchor = anchor[: len(anchor) - (node.level - 1)]
                base = ".".join(anchor + ([base] if base else []))
            names = [f"{base}.{a.name}" for a in node.names] + [base]
        for name in names:
            parts = name.split(".")
            while parts and ".".join(parts) not in known:
                parts.pop()
            if parts:
                target = ".".join(parts)
                if target != module:
                    yield target, node.lineno
                    break


def graph() -> dict[str, dict[str, int]]:
    known = modules()
    return {m: dict(imports_of(m, p, known)) for m, p in known.items()}


def upward_imports(g: dict[str, dict[str, int]]) -> list[str]:
    out = []
    for m, targets in sorted(g.items()):
        for t, line in sorted(targets.items()):
            if layer_of(t) > layer_of(m):
                out.append(
                    f"{m} (layer {LAYERS[layer_of(m)][0]}) imports {t} (layer {LAYERS[layer_of(t)][0]}) at line {line}"
                )
    return out


def adapter_crossings(g: dict[str, dict[str, int]]) -> list[str]:
    """Imports between the two adapters beyond the command line starting the web app (``CLI_REACHES_WEB``)."""
    out = []
    for m, targets in sorted(g.items()):
        for t, line in sorted(targets.items()):
            cli_to_web = m.startswith("app.cli") and t.startswith("app.web") and t not in CLI_REACHES_WEB
            web_to_cli = m.startswith("app.web") and (t == "app.cli" or t.startswith("app.cli."))
            if cli_to_web or web_to_cli:
                out.append(f"{m} imports {t} at line {line}: the adapters share code only through the engine")
    return out


def cycles(g: dict[str, dict[str, int]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    out: list[list[str]] = []
    counter = [0]
    sys.setrecursionlimit(10000)

    def visit(v: str) -> None:
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in g.get(v, {}):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(g):
        if v not in index:
            visit(v)
    return out


def main() -> int:
    g = graph()
    problems = upward_imports(g) + adapter_crossings(g) + [f"import cycle: {' -> '.join(c)}" for c in cycles(g)]
    for p in problems:
        print(p)
    print(f"{len(g)} modules, {sum(len(t) for t in g.values())} imports, {len(problems)} problems")
    return 1 if problems else 0


if __name__ == "__main__":
    raise SystemExit(main())
