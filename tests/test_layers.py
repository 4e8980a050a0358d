"""The one-way layering of docs/DESIGN.md holds: CLI -> stages -> igavatar library -> schemas, and inside
the library each package imports only packages below it, with no import cycle between modules."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
# package -> top-level packages it must never import
FORBIDDEN = {
    "igavatar": {"stages", "igavatar_cli", "typer", "rich"},
    "stages": {"igavatar_cli", "typer"},
    "schemas": {"igavatar", "stages", "igavatar_cli"},
}
# inside the library: the renderer takes fields as callables and imports no model class
FORBIDDEN_SUBPACKAGES = {"igavatar/render": {"igavatar.model"}}
# The library's packages, bottom up (docs/DESIGN.md, "Layers"): a package imports only packages of a
# lower level (and `igavatar.errors` / `igavatar.__init__`, level 0).
LIBRARY_LEVELS: tuple[tuple[str, ...], ...] = (
    ("artifacts", "geometry", "kernels"),
    ("body", "render"),
    ("skinning", "mesh", "metrics", "synth"),
    ("capture", "model", "viewer"),
    ("training",),
    ("avatar",),
)
# Synthetic-data code is for the stages that make synthetic captures, and for tests.
SYNTH_USERS = {"stages/synth.py", "stages/demo.py"}


def _imports(path: Path) -> set[str]:
    tree = ast.parse(path.read_text(encoding="utf-8"))
    names = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.add(node.module)
    return names


@pytest.mark.parametrize("package", sorted(FORBIDDEN))
def test_lower_layers_never_import_higher_ones(package):
    offenders = []
    for path in sorted((ROOT / package).rglob("*.py")):
        for name in _imports(path):
            if name.split(".")[0] in FORBIDDEN[package]:
                offenders.append(f"{path.relative_to(ROOT)} imports {name}")
    assert not offenders, offenders


@pytest.mark.parametrize("folder", sorted(FORBIDDEN_SUBPACKAGES))
def test_renderer_imports_no_model_classes(folder):
    offenders = []
    for path in sorted((ROOT / folder).rglob("*.py")):
        for name in _imports(path):
            if any(name == bad or name.startswith(bad + ".") for bad in FORBIDDEN_SUBPACKAGES[folder]):
                offenders.append(f"{path.relative_to(ROOT)} imports {name}")
    assert not offenders, offenders


def test_library_never_prints_or_exits():
    offenders = []
    for path in sorted((ROOT / "igavatar").rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id == "print":
                offenders.append(f"{path.relative_to(ROOT)}:{node.lineno} print()")
            if isinstance(node, ast.Attribute) and node.attr == "exit" and getattr(node.value, "id", "") == "sys":
                offenders.append(f"{path.relative_to(ROOT)}:{node.lineno} sys.exit")
    assert not offenders, offenders


def _library_modules() -> dict[str, Path]:
    modules = {}
    for path in sorted((ROOT / "igavatar").rglob("*.py")):
        parts = path.relative_to(ROOT).with_suffix("").parts
        modules[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return modules


def test_library_packages_import_only_lower_levels():
    level = {package: rank for rank, packages in enumerate(LIBRARY_LEVELS, start=1) for package in packages}
    packages = {p.name for p in (ROOT / "igavatar").iterdir() if p.is_dir() and (p / "__init__.py").is_file()}
    assert packages == set(level), f"every library package has a level: {sorted(packages ^ set(level))}"
    offenders = []
    for module, path in _library_modules().items():
        own = module.split(".")[1] if module.count(".") else None
        for name in _imports(path):
            parts = name.split(".")
            if parts[0] != "igavatar" or len(parts) < 2 or parts[1] not in level or parts[1] == own:
                continue
            if own is None or level[parts[1]] >= level[own]:
                offenders.append(f"{path.relative_to(ROOT)} ({own}) imports {name}")
    assert not offenders, offenders


def test_no_import_cycles_between_library_modules():
    modules = _library_modules()
    graph = {m: {n for n in _imports(p) if n in modules and n != m} for m, p in modules.items()}
    # Tarjan's strongly connected components: a component of two or more modules is a cycle.
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    cycles = []

    def visit(module: str) -> None:
        index[module] = low[module] = len(index)
        stack.append(module)
        for other in graph[module]:
            if other not in index:
                visit(other)
                low[module] = min(low[module], low[other])
            elif other in stack:
                low[module] = min(low[module], index[other])
        if low[module] == index[module]:
            component = []
            while True:
                other = stack.pop()
                component.append(other)
                if other == module:
                    break
            if len(component) > 1:
                cycles.append(sorted(component))

    for module in graph:
        if module not in index:
            visit(module)
    assert not cycles, cycles


def test_synthetic_data_code_is_used_only_by_the_synth_stages():
    offenders = []
    for folder in ("igavatar", "stages", "igavatar_cli"):
        for path in sorted((ROOT / folder).rglob("*.py")):
            relative = path.relative_to(ROOT).as_posix()
            if relative.startswith("igavatar/synth/") or relative in SYNTH_USERS:
                continue
            offenders += [f"{relative} imports {n}" for n in _imports(path) if n == "igavatar.synth" or n.startswith("igavatar.synth.")]
    assert not offenders, offenders
