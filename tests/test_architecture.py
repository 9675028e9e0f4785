"""The data flows one way: no two packages of dm2 import each other at module level (docs/architecture.md)."""

from __future__ import annotations

import ast
from collections import defaultdict
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
#: none left (issue 28): the run configuration's optimiser section is the data model's (config_optimiser.py)
KNOWN_SEAMS: set[frozenset[str]] = set()


def package_of(module: str) -> str | None:
    """``dm2_backend.optim.planes`` -> ``optim``; a top-level module (the data model) -> ``dm2_backend``."""
    parts = module.split(".")
    if parts[0] != "dm2_backend":
        return None
    return parts[1] if len(parts) > 2 else "dm2_backend"


def imports_between_packages() -> dict[str, set[str]]:
    edges: dict[str, set[str]] = defaultdict(set)
    files = [*ROOT.glob("dm2_backend/**/*.py"), *ROOT.glob("formats/*.py"), *ROOT.glob("plugins/*.py")]
    for path in files:
        rel = path.relative_to(ROOT)
        if rel.name == "__main__.py":
            continue
        source = rel.parts[0] if rel.parts[0] != "dm2_backend" else package_of(".".join(rel.with_suffix("").parts))
        for node in ast.parse(path.read_text()).body:  # module level only: a function may import lazily
            if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("dm2_backend."):
                target = package_of(node.module)
                if target and target != source:
                    edges[source].add(target)
    return edges


def test_no_two_packages_import_each_other():
    edges = imports_between_packages()
    mutual = {frozenset({a, b}) for a in edges for b in edges[a] if a in edges.get(b, set())}
    assert mutual <= KNOWN_SEAMS, sorted(tuple(sorted(p)) for p in mutual - KNOWN_SEAMS)


def test_the_package_graph_is_read():
    """The checker sees real edges (it would pass vacuously on an empty graph)."""
    edges = imports_between_packages()
    assert "dm2_backend" in edges["pipeline"] and "optim" in edges["pipeline"] and "stages" not in edges
