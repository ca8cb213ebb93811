"""The walk-throughs in notebooks/ run top to bottom (at reduced size, VEHJAX_NB_QUICK=1) and are
stored without outputs. A failing cell fails the test with the cell's error.

Executing a notebook is a small study (a kernel, the imports, a dozen compiles: 15-55 s each on
2 cores): the quick-start runs in the default suite, the others are marked ``slow`` (``pytest -m slow``). Every notebook's code is checked in the default run
without executing it: it parses, and every ``vj.<name>...`` / ``b18.<name>`` it refers to exists,
so a renamed or removed public name fails here and not first in a user's hands."""

import ast
import importlib
import os
from pathlib import Path

import pytest

nbformat = pytest.importorskip("nbformat")
nbclient = pytest.importorskip("nbclient")
pytest.importorskip("ipykernel")

NOTEBOOKS = Path(__file__).resolve().parent.parent / "notebooks"
NAMES = sorted(p.name for p in NOTEBOOKS.glob("*.ipynb"))


def test_the_walk_throughs_are_there():
    assert NAMES == ["01_quickstart.ipynb", "02_dutta2019.ipynb", "03_wang2016.ipynb",
                     "04_berntorp2018.ipynb", "05_tuning.ipynb", "06_drive.ipynb",
                     "07_limit.ipynb"]


@pytest.mark.parametrize("name", NAMES)
def test_notebook_is_stored_without_outputs(name):
    nb = nbformat.read(NOTEBOOKS / name, as_version=4)
    for i, cell in enumerate(nb.cells):
        if cell.cell_type == "code":
            assert not cell.outputs and cell.execution_count is None, \
                f"{name}: cell {i} has outputs"


RUN_BY_DEFAULT = ("01_quickstart.ipynb",)


def _code(nb):
    """The notebook's code cells as one Python source (IPython magics and shell lines dropped)."""
    lines = [line for cell in nb.cells if cell.cell_type == "code"
             for line in cell.source.splitlines() if not line.lstrip().startswith(("%", "!"))]
    return "\n".join(lines)


def _references(tree):
    """Module aliases bound by the notebook's imports of vehjax, and every attribute chain read
    from one of them (``vj.filters.ekf`` -> ("vj", ["filters", "ekf"]))."""
    aliases = {}
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                if a.name.split(".")[0] == "vehjax":
                    aliases[a.asname or a.name.split(".")[0]] = a.name if a.asname else "vehjax"
        elif isinstance(node, ast.ImportFrom) and (node.module or "").split(".")[0] == "vehjax":
            for a in node.names:
                aliases[a.asname or a.name] = f"{node.module}.{a.name}"
    chains = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Attribute) and not isinstance(getattr(node, "_parent", None),
                                                               ast.Attribute):
            parts, cur = [], node
            while isinstance(cur, ast.Attribute):
                parts.append(cur.attr)
                cur = cur.value
            if isinstance(cur, ast.Name) and cur.id in aliases:
                chains.append((cur.id, parts[::-1]))
    return aliases, chains


def _resolve(dotted):
    try:
        return importlib.import_module(dotted)
    except ImportError:
        mod, _, name = dotted.rpartition(".")
        return getattr(importlib.import_module(mod), name)


def _missing(source, filename="<cell>"):
    """The ``alias.a.b`` references of ``source`` into vehjax that do not exist (a chain is
    followed through modules and classes; past a value, e.g. a result's field, it is not)."""
    tree = ast.parse(source, filename=filename)
    for node in ast.walk(tree):
        for child in ast.iter_child_nodes(node):
            child._parent = node
    aliases, chains = _references(tree)
    missing = []
    for alias, parts in chains:
        obj = _resolve(aliases[alias])
        for i, attr in enumerate(parts):
            if isinstance(obj, type(ast)) and not hasattr(obj, attr):
                try:  # a subpackage its parent's __init__ does not import
                    obj = importlib.import_module(f"{obj.__name__}.{attr}")
                    continue
                except ImportError:
                    pass
            if not hasattr(obj, attr):
                missing.append(f"{alias}.{'.'.join(parts[:i + 1])}")
                break
            obj = getattr(obj, attr)
            if not isinstance(obj, (type(ast), type)):
                break
    return missing


def test_the_static_check_finds_a_missing_name():
    src = ("import vehjax as vj\nfrom vehjax.reproduce import berntorp2018 as b18\n"
           "vj.filters.ekf\nvj.filters.no_such_filter\nb18.no_such_constant\nvj.run(1).x.y\n")
    assert _missing(src) == ["vj.filters.no_such_filter", "b18.no_such_constant"]


@pytest.mark.parametrize("name", NAMES)
def test_notebook_code_parses_and_its_vehjax_names_exist(name):
    source = _code(nbformat.read(NOTEBOOKS / name, as_version=4))
    assert "import vehjax" in source or "from vehjax" in source, f"{name} does not import vehjax"
    assert _missing(source, name) == []


def _mark(name):
    return () if name in RUN_BY_DEFAULT else (pytest.mark.slow,)


@pytest.mark.parametrize("name", [pytest.param(n, marks=_mark(n)) for n in NAMES])
def test_notebook_runs(name, monkeypatch):
    monkeypatch.setenv("VEHJAX_NB_QUICK", "1")
    monkeypatch.setenv("MPLBACKEND", "module://matplotlib_inline.backend_inline")
    nb = nbformat.read(NOTEBOOKS / name, as_version=4)
    client = nbclient.NotebookClient(nb, timeout=600, kernel_name="python3",
                                     resources={"metadata": {"path": str(NOTEBOOKS)}})
    client.execute()  # raises CellExecutionError naming the cell and its traceback
    figures = sum("image/png" in out.get("data", {})
                  for cell in nb.cells if cell.cell_type == "code" for out in cell.outputs)
    assert figures >= 1, f"{name} drew no figure"
    assert os.environ["VEHJAX_NB_QUICK"] == "1"
