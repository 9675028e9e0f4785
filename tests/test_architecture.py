"""Imports go down the declared layers (``dm2_backend/layers.py``; docs/architecture.md): every import of every
module, at module level and inside functions, reaches a lower layer or stays in its own package. Modules loaded by
name at run time (``importlib``, the plugins' and formats' entry points) are not imports and are not checked."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

from dm2_backend.layers import LAYERS, layer_of, unit_of

ROOT = Path(__file__).resolve().parents[1]


def module_name(path: Path) -> str:
    """``formats/bag.py`` -> ``dm2_backend.formats.bag`` (installed under dm2_backend); packages end in __init__."""
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    return ".".join(parts if parts[0] == "dm2_backend" else ["dm2_backend", *parts]).removesuffix(".__init__")


def imported(source: str, module: str, package: bool = False) -> list[tuple[int, str]]:
    """(line, dotted name) of every import in ``source`` (relative ones resolved against ``module``, a package's
    ``__init__`` when ``package``), anywhere in the file."""
    package_parts = module.split(".") if package else module.split(".")[:-1]
    found = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.ImportFrom):
            if node.level > len(package_parts):
                raise ValueError(f"{module}:{node.lineno}: a relative import above the package")
            base = ".".join(package_parts[:len(package_parts) - node.level + 1]) if node.level else ""
            target = ".".join(p for p in (base, node.module) if p)
            found += [(node.lineno, f"{target}.{alias.name}") for alias in node.names]
        elif isinstance(node, ast.Import):
            found += [(node.lineno, alias.name) for alias in node.names]
    return found


def upward_imports(sources: dict[str, tuple[str, bool]] | None = None) -> list[str]:
    """``module:line imports name (layer a -> layer b)`` for every import that does not go down; ``sources``:
    module -> (its text, whether it is a package), by default every module of dm2."""
    if sources is None:
        sources = {module_name(p): (p.read_text(), p.name == "__init__.py") for p in dm2_files()}
    wrong = []
    for module, (text, package) in sources.items():
        source = unit_of(module)
        for line, name in imported(text, module, package):
            target = unit_of(name)
            if target is None or target == source:
                continue
            if layer_of(target) >= layer_of(source):
                wrong.append(f"{module}:{line} imports {name} ({LAYERS[layer_of(source)][0]} -> "
                             f"{LAYERS[layer_of(target)][0]})")
    return wrong


def dm2_files() -> list[Path]:
    return sorted([*ROOT.glob("dm2_backend/**/*.py"), *ROOT.glob("formats/**/*.py"), *ROOT.glob("plugins/**/*.py")])


def test_every_import_goes_down_the_layers():
    assert upward_imports() == []


def test_every_package_is_in_a_layer():
    units = {unit_of(module_name(p)) for p in dm2_files()}
    for unit in units:
        layer_of(unit)  # raises for a package nobody placed
    declared = {u for _, layer in LAYERS for u in layer}
    assert declared == units, declared ^ units


def test_the_checker_sees_imports_inside_functions_sideways_and_relative():
    sources = {
        "dm2_backend.kernel.planes": ("def f():\n    from dm2_backend.optim import dense\n", False),
        "dm2_backend.optim.dense": ("from dm2_backend.evaluation import plots\n", False),
        "dm2_backend.maps.x": ("from ..pipeline import refine\nfrom ..evaluation import plots\n", False),
        "dm2_backend.pipeline.y": ("import dm2_backend.cli.main\nfrom dm2_backend.kernel import planes\n", False),
        "dm2_backend.kernel": ("from .planes import x\nfrom ..prepare import steps\n", True),
    }
    wrong = upward_imports(sources=sources)
    assert [w.split(" (")[0] for w in wrong] == [
        "dm2_backend.kernel.planes:2 imports dm2_backend.optim.dense",
        "dm2_backend.optim.dense:1 imports dm2_backend.evaluation.plots",
        "dm2_backend.maps.x:1 imports dm2_backend.pipeline.refine",
        "dm2_backend.pipeline.y:1 imports dm2_backend.cli.main",
        "dm2_backend.kernel:2 imports dm2_backend.prepare.steps",
    ]


def test_the_real_graph_is_read():
    """The checker reads real edges, lazy ones included (it would pass vacuously on an empty graph)."""
    lazy = imported((ROOT / "dm2_backend/maps/rerun_view.py").read_text(), "dm2_backend.maps.rerun_view")
    assert any(name.startswith("dm2_backend.evaluation.") for _, name in lazy)
    assert len(imported((ROOT / "dm2_backend/pipeline/refine.py").read_text(), "dm2_backend.pipeline.refine")) > 10


@pytest.mark.parametrize("name", ["numpy", "dm2_backend_other.x"])
def test_outside_modules_are_not_dm2s(name):
    assert unit_of(name) is None


def test_the_architecture_page_draws_the_declared_layers():
    """docs/architecture.md's diagram lists the layers of ``LAYERS``, top first, with their packages."""
    page = (ROOT / "docs" / "architecture.md").read_text()
    diagram = page.split("## Layers", 1)[1].split("```")[1].strip().splitlines()
    folders = {"dm2_backend": None}
    expected = [(name, [f"{u}/" for u in units if folders.get(u, u)]) for name, units in reversed(LAYERS)]
    drawn = [(line[:16].strip(), [w for w in line[16:].split() if w.endswith("/")]) for line in diagram]
    assert drawn == expected


def test_every_package_folder_is_installed():
    """pyproject.toml lists every folder of dm2 that holds an ``__init__.py`` (an editable install would hide a
    missing one; a wheel would lack it)."""
    import tomllib

    listed = set(tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"])
    folders = {module_name(p.parent / "x.py").removesuffix(".x")
               for p in dm2_files() if p.name == "__init__.py"}
    assert listed == folders, listed ^ folders
