"""Each heavy dependency lives in one layer; imports point down only (DESIGN.md, Layers)."""

import ast
from pathlib import Path

SRC = Path(__file__).resolve().parents[1] / "src" / "massview"
ORDER = ["core", "data", "lod", "render", "parallel", "systems", "app"]
OWNER = {"moderngl": "render", "glcontext": "render", "mpi4py": "parallel", "zarr": "data", "rasterio": "data", "trimesh": "data", "numba": "data"}


def _imports(path: Path):
    tree = ast.parse(path.read_text())
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                yield a.name, 0
        elif isinstance(node, ast.ImportFrom):
            yield node.module or "", node.level


def _layer(path: Path) -> str | None:
    rel = path.relative_to(SRC).parts
    return rel[0] if len(rel) > 1 and rel[0] in ORDER else None


def test_heavy_dependencies_stay_in_their_layer():
    bad = []
    for f in SRC.rglob("*.py"):
        layer = _layer(f)
        for mod, level in _imports(f):
            top = mod.split(".")[0]
            if level == 0 and top in OWNER and OWNER[top] != layer:
                bad.append(f"{f.relative_to(SRC)} imports {mod} (belongs to {OWNER[top]}/)")
    assert not bad, "\n".join(bad)


def test_imports_point_down_only():
    bad = []
    for f in SRC.rglob("*.py"):
        layer = _layer(f)
        if layer is None:
            continue
        pkg_depth = len(f.relative_to(SRC).parts) - 1
        for mod, level in _imports(f):
            if level == 0:
                if not mod.startswith("massview."):
                    continue
                target = mod.split(".")[1]
            elif level > pkg_depth:
                target = mod.split(".")[0] if mod else None
            else:
                continue  # same layer
            if target in ORDER and ORDER.index(target) > ORDER.index(layer):
                bad.append(f"{f.relative_to(SRC)} ({layer}) imports {target}/")
    assert not bad, "\n".join(bad)


def test_core_imports_numpy_only():
    """core/ is "numpy only" (DESIGN.md): besides the standard library and massview itself it
    imports numpy and nothing else (the walkthrough's planner, which needs scipy, lives in lod/)."""
    import sys

    bad = []
    for f in (SRC / "core").rglob("*.py"):
        for mod, level in _imports(f):
            top = mod.split(".")[0]
            if level == 0 and top and top not in sys.stdlib_module_names and top not in ("numpy", "massview", "__future__"):
                bad.append(f"{f.relative_to(SRC)} imports {mod}")
    assert not bad, "\n".join(bad)
