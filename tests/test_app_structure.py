"""The app is a shell over the API: benchmarks in a registry, no private reach-ins, no cycles."""

import argparse
import ast
from pathlib import Path

import massview
from massview.app.bench import BENCHES
from massview.app.cli import build_parser

SRC = Path(massview.__file__).parent
APP = SRC / "app"


def _tree(path: Path) -> ast.AST:
    return ast.parse(path.read_text(encoding="utf-8"))


def test_benchmarks_come_from_the_registry():
    assert {"composite", "terrain", "ingest"} <= set(BENCHES)
    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))  # noqa: SLF001 - argparse has no public accessor
    bench = sub.choices["bench"]
    names = next(a for a in bench._actions if isinstance(a, argparse._SubParsersAction)).choices  # noqa: SLF001
    assert set(names) == set(BENCHES)
    for name, mod in BENCHES.items():
        assert callable(mod.add_arguments) and callable(mod.run), name
        assert Path(mod.__file__).parent == APP / "bench"


def test_no_private_attribute_of_another_object_is_used_in_app_or_api():
    """`obj._name` only on self/cls (the benchmarks used TerrainSystem._renderers() once)."""
    bad = []
    for f in [SRC / "api.py", *APP.rglob("*.py")]:
        for node in ast.walk(_tree(f)):
            if isinstance(node, ast.Attribute) and node.attr.startswith("_") and not node.attr.startswith("__"):
                owner = node.value
                if not (isinstance(owner, ast.Name) and owner.id in ("self", "cls", "argparse")):
                    bad.append(f"{f.relative_to(SRC)}:{node.lineno} .{node.attr}")
    assert not bad, "\n".join(bad)


def test_only_the_entry_point_imports_the_cli():
    """demo, viewer, benchmarks and the API call massview.api, never the CLI (no import cycle)."""
    importers = []
    for f in [SRC / "api.py", *APP.rglob("*.py")]:
        for node in ast.walk(_tree(f)):
            if isinstance(node, ast.ImportFrom) and node.module and node.module.split(".")[-1] == "cli" \
                    or isinstance(node, ast.ImportFrom) and any(a.name == "cli" for a in node.names):
                importers.append(str(f.relative_to(SRC)))
    assert importers == [], importers
    for name in ("demo.py", "view_cmd.py", "bench/terrain.py"):
        assert "api" in (APP / name).read_text(encoding="utf-8")
