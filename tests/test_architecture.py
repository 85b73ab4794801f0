"""The package's structure: rooms (top-level folders and modules) import only the rooms below them."""

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "src" / "mapsqueeze"

FLOORS = {
    "errors": 0, "shared": 0, "version": 0,
    "geometry": 1,
    "io": 2, "metrics": 2,
    "data": 3, "model": 3, "baselines": 3,
    "codec": 4,
    "api": 5,
    "train": 6,
    "benchmark": 7, "demo": 7, "view": 7,
    "cli": 8,
    "__init__": 9, "__main__": 9,
}
"""The floor of every room (a top-level folder or module of src/mapsqueeze); docs/architecture.md explains them.
A room may import rooms on lower floors only: never a room above it, nor another room on its own floor."""


def room_of(module: str) -> str:
    """The room of a dotted module name inside the package ("mapsqueeze.io.formats" -> "io")."""
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else "__init__"


def imported_modules(path: Path, root: Path) -> list[tuple[str, int]]:
    """(absolute module name, line) of every import in a file of the package at `root`, also inside functions."""
    package = ".".join(("mapsqueeze", *path.relative_to(root).with_suffix("").parts))
    if path.name == "__init__.py":
        package = package.rsplit(".", 1)[0] + ".__init__"
    found = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            found += [(alias.name, node.lineno) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")[: -node.level]
                base = ".".join([*anchor, base] if base else anchor)
            if base == "mapsqueeze":  # `from mapsqueeze import api`: the names are the rooms
                found += [(f"mapsqueeze.{alias.name}", node.lineno) for alias in node.names]
            else:
                found.append((base, node.lineno))
    return [(module, line) for module, line in found if module == "mapsqueeze" or module.startswith("mapsqueeze.")]


def upward_imports(package: Path) -> list[str]:
    """Every import of a room on the same or a higher floor, as 'file:line: a (floor) imports b (floor)'."""
    problems = []
    for path in sorted(package.rglob("*.py")):
        relative = path.relative_to(package)
        room = relative.parts[0].removesuffix(".py")
        if room not in FLOORS:
            problems.append(f"{relative}: room {room!r} has no floor in FLOORS")
            continue
        for module, line in imported_modules(path, package):
            target = room_of(module)
            if target == room:
                continue
            if target not in FLOORS:
                problems.append(f"{relative}:{line}: imports {module}, whose room {target!r} has no floor")
            elif FLOORS[target] >= FLOORS[room]:
                problems.append(f"{relative}:{line}: {room} (floor {FLOORS[room]}) imports {module} "
                                f"(floor {FLOORS[target]})")
    return problems


def test_rooms_import_only_rooms_below_them():
    assert upward_imports(PACKAGE) == []


def test_an_upward_import_is_caught(tmp_path):
    package = tmp_path / "mapsqueeze"
    (package / "geometry").mkdir(parents=True)
    (package / "geometry" / "__init__.py").write_text("")
    (package / "geometry" / "normals.py").write_text("def f():\n    from mapsqueeze.io import validate_points\n")
    (package / "io").mkdir()
    (package / "io" / "formats.py").write_text("from ..geometry import bounds\nfrom . import atomic\n")
    (package / "data").mkdir()
    (package / "data" / "mapping.py").write_text("from mapsqueeze.model import load_model\n")
    (package / "attic.py").write_text("")
    assert upward_imports(package) == [
        "attic.py: room 'attic' has no floor in FLOORS",
        "data/mapping.py:1: data (floor 3) imports mapsqueeze.model (floor 3)",
        "geometry/normals.py:2: geometry (floor 1) imports mapsqueeze.io (floor 2)",
    ]


MAX_SOURCE_LINES = 500


def test_no_source_file_is_over_500_lines():
    long_files = {str(path.relative_to(PACKAGE)): n for path in sorted(PACKAGE.rglob("*.py"))
                  if (n := len(path.read_text().splitlines())) > MAX_SOURCE_LINES}
    assert long_files == {}, f"split these files (lines): {long_files}"
