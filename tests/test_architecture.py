"""The layering of DESIGN.md and docs/architecture.md, checked on the imports:

- autonomy/ imports neither drivers nor companion, nor any I/O;
- drivers/ never imports companion;
- the flight process (companion/flight/) never imports the simulator, nor the tools around it;
- the config adds the simulator's tables from the simulator's own list of them.
"""

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
AUTONOMY = ROOT / "autonomy"

#: Top-level modules autonomy/ must never import: the outer layers, event loops, wires, clocks.
FORBIDDEN = frozenset({"drivers", "companion", "asyncio", "socket", "time", "serial"})


def forbidden_imports(source: str, forbidden=FORBIDDEN) -> list[tuple[int, str]]:
    """(line, module) of every absolute import in ``source`` that is ``forbidden`` or inside a
    forbidden package (names may be dotted: ``drivers.sim`` forbids ``drivers.sim.world``)."""
    found = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            modules = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            modules = [node.module]
        else:
            continue
        found += [(node.lineno, m) for m in modules if _inside(m, forbidden)]
    return sorted(found)


def _inside(module: str, packages) -> bool:
    parts = module.split(".")
    return any(".".join(parts[:k]) in packages for k in range(1, len(parts) + 1))


def offences(folder: Path, forbidden) -> list[str]:
    files = sorted(folder.rglob("*.py"))
    assert files, f"no Python files found under {folder}"
    return [f"{path.relative_to(ROOT)}:{line} imports {module}"
            for path in files
            for line, module in forbidden_imports(path.read_text(encoding="utf-8"), forbidden)]


def test_checker_finds_every_form_of_forbidden_import():
    source = (
        "import numpy as np\n"
        "import os, time\n"
        "from drivers.mavlink import link\n"
        "import companion.flight.app as app\n"
        "from . import geometry\n"
        "from timeit import default_timer\n"
        "def f():\n"
        "    import asyncio\n"
    )
    assert forbidden_imports(source) == [
        (2, "time"), (3, "drivers.mavlink"), (4, "companion.flight.app"), (8, "asyncio"),
    ]


def test_dotted_packages_forbid_what_is_inside_them_only():
    source = "from drivers.sim.world import World\nimport drivers.simple\nimport drivers.mavlink\n"
    assert forbidden_imports(source, frozenset({"drivers.sim"})) == [(1, "drivers.sim.world")]


def test_autonomy_imports_no_outer_layer_or_io():
    found = offences(AUTONOMY, FORBIDDEN)
    assert not found, "autonomy/ must stay pure (DESIGN.md):\n" + "\n".join(found)


def test_drivers_never_import_the_application():
    found = offences(ROOT / "drivers", frozenset({"companion"}))
    assert not found, "drivers/ is below companion/ (DESIGN.md):\n" + "\n".join(found)


def test_the_flight_process_never_imports_the_simulator_or_the_tools():
    found = offences(ROOT / "companion" / "flight",
                     frozenset({"drivers.sim", "companion.tools", "companion.launch",
                                "companion.cli"}))
    assert not found, ("companion/flight/ flies real and simulated vehicles alike "
                       "(docs/architecture.md):\n" + "\n".join(found))


def test_the_config_takes_the_simulators_tables_from_the_simulators_own_list():
    source = (ROOT / "companion" / "config.py").read_text(encoding="utf-8")
    found = [module for _, module in forbidden_imports(source, frozenset({"drivers.sim"}))]
    assert found == ["drivers.sim.options"], found
