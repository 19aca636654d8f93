"""Who may import whom, read from the sources' import statements.

- Every package installs under the project's namespace (cloneguard.container,
  cloneguard.harness, cloneguard.faults, cloneguard.bench) while its folder
  stays at the repository's top level. From the repository root a bare
  `import harness` would still find the folder and load a second copy of
  every module (and of the C extensions' Python state) beside the installed
  one, so no source may use the bare names.
- The product never depends on its test rig.
- The harness treats the container as a black box: it never imports it.
"""

import ast
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent
FOLDERS = ("container", "harness", "faults", "bench")
SOURCES = sorted(p for top in (*FOLDERS, "scenarios", "tests", "scripts") for p in (REPO / top).rglob("*.py"))


def imported_modules(path: Path) -> list[str]:
    """Absolute module names a file imports (relative imports resolve
    inside the file's own package and are left out)."""
    names = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            names += [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names.append(node.module)
    return names


def offenders(paths, bad) -> list[str]:
    return [f"{p.relative_to(REPO)}: {m}" for p in paths for m in imported_modules(p) if bad(m)]


def test_the_sources_are_read():
    assert len(SOURCES) > 100
    assert "cloneguard.harness.factory" in imported_modules(REPO / "tests" / "test_product_install.py")


def test_no_source_imports_a_bare_top_level_name():
    bare = offenders(SOURCES, lambda m: m.split(".")[0] in FOLDERS)
    assert bare == [], "import them as cloneguard.<name>: " + ", ".join(bare)


@pytest.mark.parametrize(
    "folder, forbidden",
    [
        ("container", ("cloneguard.harness", "cloneguard.faults", "cloneguard.bench")),
        ("harness", ("cloneguard.container",)),
    ],
)
def test_dependencies_run_one_way(folder, forbidden):
    found = offenders(
        sorted((REPO / folder).rglob("*.py")), lambda m: any(m == f or m.startswith(f + ".") for f in forbidden)
    )
    assert found == []
