"""The walk-throughs in notebooks/ run top to bottom (at reduced size, VEHJAX_NB_QUICK=1) and are
stored without outputs. A failing cell fails the test with the cell's error."""

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
                     "04_berntorp2018.ipynb", "05_tuning.ipynb", "06_drive.ipynb"]


@pytest.mark.parametrize("name", NAMES)
def test_notebook_is_stored_without_outputs(name):
    nb = nbformat.read(NOTEBOOKS / name, as_version=4)
    for i, cell in enumerate(nb.cells):
        if cell.cell_type == "code":
            assert not cell.outputs and cell.execution_count is None, \
                f"{name}: cell {i} has outputs"


@pytest.mark.parametrize("name", NAMES)
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
