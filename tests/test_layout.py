"""The package layout's promises (issue 20), checked on the source text: scripts outside the
package use only public names, and matplotlib is imported by the plotting module alone."""

import ast
import pathlib
import subprocess
import sys

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
PLOTTING = ROOT / "src" / "hdjax" / "_workflows" / "plots.py"


def _imports(path: pathlib.Path) -> list[str]:
    """Every module an `import` or `from … import` of the file names, `from hdjax import _x` as `hdjax._x`."""
    names = []
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            names += [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names.append(node.module)
            names += [f"{node.module}.{a.name}" for a in node.names if a.name.startswith("_")]
    return names


@pytest.mark.parametrize("folder", ["experiments", "benchmarks", "scripts"])
def test_scripts_outside_the_package_use_only_public_names(folder):
    files = sorted((ROOT / folder).rglob("*.py"))
    assert files, f"no scripts found in {folder}/"
    private = {f"{p.relative_to(ROOT)}: {m}" for p in files for m in _imports(p)
               if m.startswith("hdjax.") and any(part.startswith("_") for part in m.split(".")[1:])}
    assert not private, f"scripts import private hdjax names (export them from hdjax instead): {sorted(private)}"


def test_matplotlib_is_imported_by_the_plotting_module_alone():
    found = {str(p.relative_to(ROOT)) for p in (ROOT / "src" / "hdjax").rglob("*.py")
             if any(m.split(".")[0] == "matplotlib" for m in _imports(p))}
    assert found == {str(PLOTTING.relative_to(ROOT))}
    # and `import hdjax` does not load it (the commands load it only when they draw)
    out = subprocess.run([sys.executable, "-c", "import sys, hdjax; print('matplotlib' in sys.modules)"],
                         capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"
