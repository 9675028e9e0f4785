"""dm2's layers, bottom first. An import goes down to a lower layer or stays inside its own package; packages of
one layer stand side by side and import none of each other (``tests/test_architecture.py`` checks every import,
module level and inside functions; ``docs/reference/layers.md`` is drawn from this table)."""

from __future__ import annotations

#: (layer, its packages), bottom first; ``dm2_backend`` is the package's root (its version and this table)
LAYERS: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("runtime", ("dm2_backend", "runtime")),
    ("kernel", ("kernel",)),
    ("adapters", ("formats", "algorithms")),
    ("plugins", ("plugins",)),
    ("configuration", ("config",)),
    ("stages", ("prepare", "optim", "baselines", "evaluation")),
    ("products", ("maps", "simulate")),
    ("pipeline", ("pipeline",)),
    ("command line", ("cli",)),
)


def unit_of(module: str) -> str | None:
    """The package a dotted module name belongs to (``dm2_backend.kernel.planes`` -> ``kernel``; ``python -m``'s
    ``__main__`` -> ``cli``); None outside dm2."""
    parts = module.split(".")
    if parts[0] != "dm2_backend":
        return None
    if len(parts) == 1 or parts[1] in ("__version__", "layers"):
        return "dm2_backend"
    if parts[1] == "__main__":
        return "cli"
    return parts[1]


def layer_of(unit: str) -> int:
    """The layer's index (0 at the bottom) of a package named by :func:`unit_of`."""
    for index, (_, units) in enumerate(LAYERS):
        if unit in units:
            return index
    raise KeyError(f"package {unit!r} is in no layer of dm2_backend.layers.LAYERS")
