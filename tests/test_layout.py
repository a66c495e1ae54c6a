"""The package's layers import downwards only (docs/layout.md): a lower layer never reaches up."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "mixer_nerf"

# Each layer and the package-level modules and subpackages it may import.
ALLOWED = {
    "ops": {"_extension", "_sources"},
    "model": {"ops"},
    "data": set(),
    "render": {"ops", "data"},
    "train": {"ops", "data", "model", "render", "metrics", "lpips_alex", "numpy_pickle"},
}


def imported_layers(path: Path, layer: str) -> set[str]:
    """Top-level names of mixer_nerf that ``path`` (inside subpackage ``layer``) imports."""
    depth = len(path.relative_to(PACKAGE).parts) - 1  # of the file's package: 1 for mixer_nerf/<layer>/x.py
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.level == depth + 1:  # relative to mixer_nerf itself
            found |= {node.module.split(".")[0]} if node.module else {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom) and not node.level and (node.module or "").startswith("mixer_nerf."):
            found.add(node.module.split(".")[1])
        elif isinstance(node, ast.Import):
            found |= {a.name.split(".")[1] for a in node.names if a.name.startswith("mixer_nerf.")}
    return found - {layer}


@pytest.mark.parametrize("layer", sorted(ALLOWED))
def test_a_layer_imports_only_the_layers_below_it(layer):
    reaching_up = {
        f"{path.relative_to(PACKAGE)} imports {name}"
        for path in sorted((PACKAGE / layer).rglob("*.py"))
        for name in imported_layers(path, layer) - ALLOWED[layer]
    }
    assert not reaching_up, sorted(reaching_up)
