"""The purity rule of DESIGN.md: autonomy/ imports neither drivers nor companion, nor any I/O."""

import ast
from pathlib import Path

AUTONOMY = Path(__file__).resolve().parent.parent / "autonomy"

#: Top-level modules autonomy/ must never import: the outer layers, event loops, wires, clocks.
FORBIDDEN = frozenset({"drivers", "companion", "asyncio", "socket", "time", "serial"})


def forbidden_imports(source: str) -> list[tuple[int, str]]:
    """(line, module) of every absolute import in ``source`` whose top-level name is forbidden."""
    found = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            modules = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            modules = [node.module]
        else:
            continue
        found += [(node.lineno, m) for m in modules if m.split(".")[0] in FORBIDDEN]
    return sorted(found)


def test_checker_finds_every_form_of_forbidden_import():
    source = (
        "import numpy as np\n"
        "import os, time\n"
        "from drivers.mavlink import link\n"
        "import companion.app as app\n"
        "from . import geometry\n"
        "from timeit import default_timer\n"
        "def f():\n"
        "    import asyncio\n"
    )
    assert forbidden_imports(source) == [
        (2, "time"), (3, "drivers.mavlink"), (4, "companion.app"), (8, "asyncio"),
    ]


def test_autonomy_imports_no_outer_layer_or_io():
    files = sorted(AUTONOMY.rglob("*.py"))
    assert files, f"no Python files found under {AUTONOMY}"
    offences = [
        f"{path.relative_to(AUTONOMY.parent)}:{line} imports {module}"
        for path in files
        for line, module in forbidden_imports(path.read_text(encoding="utf-8"))
    ]
    assert not offences, "autonomy/ must stay pure (DESIGN.md):\n" + "\n".join(offences)
