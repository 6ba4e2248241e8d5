"""Who may import whom (docs/architecture.md, "Packages"): checked on the source text.

Every `import arlight.X` / `from arlight.X import ...` in a package's files, at any depth (also
inside functions), must name a package that the table allows. The table is one way: no cycles.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

# folder -> subpackage name, as pyproject's package-dir maps them (arlight/core is a folder
# of arlight/ itself). A file belongs to the deepest folder that holds it.
FOLDERS = {
    "arlight/core": "core",
    "pipeline": "pipeline",
    "protocols": "protocols",
    "sources": "sources",
    "client": "client",
    "server": "server",
    "arlight": "arlight",
}

# package -> the arlight packages it may import. "core" = arlight.core, the lowest layer
# (the edge checks, the frame path's typed contracts, the camera, the frame types) that every
# other package may import; "version" = arlight.__version__
ALLOWED = {
    "core": set(),
    "pipeline": {"core"},
    "protocols": {"core", "version"},
    "sources": {"core", "pipeline", "protocols", "version"},
    "server": {"core", "pipeline", "protocols", "version"},
    "client": {"core", "pipeline", "protocols", "sources", "version"},
    "arlight": {
        "core",
        "pipeline",
        "protocols",
        "sources",
        "server",
        "client",
        "version",
        "arlight",
    },
}


def _package_of(path: Path) -> str:
    rel = path.relative_to(ROOT).as_posix()
    folder = max((f for f in FOLDERS if rel.startswith(f + "/")), key=len)
    return FOLDERS[folder]


def _imported_packages(path: Path) -> set[str]:
    """arlight packages named by the imports of one file."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        names: list[str] = []
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names = [node.module]
            if node.module == "arlight":
                names = [f"arlight.{a.name}" for a in node.names]
        for name in names:
            parts = name.split(".")
            if parts[0] != "arlight":
                continue
            sub = parts[1] if len(parts) > 1 else "version"
            if sub == "__version__":
                sub = "version"
            elif sub not in ALLOWED:  # a module of the top package: cli, demo, bench, ...
                sub = "arlight"
            found.add(sub)
    return found


def _source_files():
    found: set[Path] = set()
    for folder in FOLDERS:
        base = ROOT / folder
        if base.is_dir():
            found.update(base.rglob("*.py"))
    yield from sorted(found)


@pytest.mark.parametrize("path", list(_source_files()), ids=lambda p: str(p.relative_to(ROOT)))
def test_imports_follow_the_package_table(path: Path):
    package = _package_of(path)
    imported = _imported_packages(path) - {package}
    forbidden = imported - ALLOWED[package]
    assert not forbidden, (
        f"{path.relative_to(ROOT)} ({package}) imports {sorted(forbidden)}; "
        f"allowed: {sorted(ALLOWED[package])}"
    )


def _top_modules(path: Path) -> set[str]:
    tree = ast.parse(path.read_text())
    modules = {
        a.name.split(".")[0] for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names
    }
    modules |= {
        n.module.split(".")[0] for n in ast.walk(tree) if isinstance(n, ast.ImportFrom) and n.module
    }
    return modules


def test_checks_module_needs_nothing_but_numpy():
    modules = _top_modules(ROOT / "arlight" / "core" / "checks.py")
    assert modules <= {"__future__", "math", "typing", "numpy"}, modules


def test_contracts_module_needs_nothing_but_the_standard_library():
    modules = _top_modules(ROOT / "arlight" / "core" / "contracts.py")
    assert modules <= {"__future__", "collections", "dataclasses", "math", "typing"}, modules


def test_package_table_has_no_cycles():
    def reaches(a: str, b: str, seen: frozenset = frozenset()) -> bool:
        return any(
            n == b or (n not in seen and reaches(n, b, seen | {n}))
            for n in ALLOWED.get(a, ())
            if n != "version"
        )

    for package in ALLOWED:
        if package == "arlight":
            continue  # the CLI sits on top: nothing imports it
        assert not reaches(package, package), package


def test_importing_the_pipeline_leaves_the_warning_filters_alone():
    """No arlight module changes the process's warning filters when imported."""
    import subprocess
    import sys

    code = f"""
import sys, warnings
callers = []
def spy(original):
    def wrapper(*args, **kwargs):
        callers.append(sys._getframe(1).f_code.co_filename)
        return original(*args, **kwargs)
    return wrapper
warnings.filterwarnings = spy(warnings.filterwarnings)
warnings.simplefilter = spy(warnings.simplefilter)
import arlight.pipeline.pipeline
ours = [c for c in callers if c.startswith({str(ROOT)!r}) and "/.venv/" not in c]
assert not ours, ours
"""
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
