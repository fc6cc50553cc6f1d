"""The notebooks in notebooks/ execute without error in their small
configuration (``JDEM_SMALL=1``, set by tests/conftest.py) and write their files.

:func:`execute_notebook` runs a notebook with nbclient in a python3 kernel
(jupyter_client starts the kernelspec's ``python`` as this interpreter, so the
kernel sees the same environment and jdem), in a given working directory.
"""
import os
import pathlib
import shutil
import sys

import pytest

NOTEBOOKS = pathlib.Path(__file__).resolve().parents[1] / "notebooks"


def execute_notebook(name, workdir, *, timeout=600, env=None):
    """Execute ``notebooks/<name>`` with its working directory ``workdir``.

    The notebook is copied into ``workdir`` (so relative outputs land there),
    run cell by cell in a ``python3`` kernel with the current environment plus
    ``env``, and the executed notebook is written beside it as
    ``executed_<name>``.  A failing cell raises ``nbclient``'s
    ``CellExecutionError`` with the cell's traceback.  Returns the executed
    notebook (``nbformat.NotebookNode``).
    """
    import nbformat
    from nbclient import NotebookClient

    workdir = pathlib.Path(workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    src = workdir / name
    shutil.copy(NOTEBOOKS / name, src)
    nb = nbformat.read(src, as_version=4)
    saved = dict(os.environ)
    os.environ.update(env or {})
    os.environ.setdefault("MPLBACKEND", "Agg")
    try:
        client = NotebookClient(nb, kernel_name="python3", timeout=timeout,
                                resources={"metadata": {"path": str(workdir)}})
        client.execute()
    finally:
        os.environ.clear()
        os.environ.update(saved)
    nbformat.write(nb, workdir / f"executed_{name}")
    return nb


def _kernel_python(workdir):
    """``sys.prefix`` of a python3 kernel (to check it is this environment)."""
    import nbformat
    from nbclient import NotebookClient

    nb = nbformat.v4.new_notebook(cells=[nbformat.v4.new_code_cell(
        "import sys; print(sys.prefix)")])
    NotebookClient(nb, kernel_name="python3", timeout=120,
                   resources={"metadata": {"path": str(workdir)}}).execute()
    return nb.cells[0].outputs[0]["text"].strip()


# slow (~60 s): the sweep itself is tested in tests/test_sweep.py
@pytest.mark.slow
def test_sweep_notebook_small(tmp_path):
    assert os.environ.get("JDEM_SMALL") == "1"
    nb = execute_notebook("sweep.ipynb", tmp_path, env={"JDEM_SMALL": "1"})
    out = tmp_path / "sweep_results"
    for png in ("sweep_heatmaps.png", "peak_stress.png", "critical_strain.png",
                "sweep_curves.png"):
        assert (out / png).stat().st_size > 5_000, png
    from jdem import sweep as sw

    table = sw.load_sweep(out / "sweep.h5")
    assert table["peak_stress"].shape == (4,)          # the 2 x 2 grid
    assert table.attrs["parameters"] == ["eps_lim", "T0"]
    text = "".join(o.get("text", "") for c in nb.cells if c.cell_type == "code"
                   for o in c.get("outputs", []))
    assert "small configuration" in text


def test_notebooks_are_committed_without_outputs():
    import nbformat

    for path in sorted(NOTEBOOKS.glob("*.ipynb")):
        nb = nbformat.read(path, as_version=4)
        for cell in nb.cells:
            if cell.cell_type == "code":
                assert not cell.outputs and cell.execution_count is None, path.name


def test_kernel_runs_this_environment(tmp_path):
    assert _kernel_python(tmp_path) == sys.prefix


# slow (~150 s): the same calibration path runs in tests/test_cli.py
@pytest.mark.slow
def test_calibration_notebook_runs(tmp_path):
    execute_notebook("calibration.ipynb", tmp_path)
    assert (tmp_path / "calibration.png").stat().st_size > 0
    from jdem import calibrate

    back = calibrate.load_calibration(tmp_path / "calibration.h5")
    assert set(back["values"]) == {"E", "strength"}
    assert back["history"]["loss"][-1] <= back["history"]["loss"][0]
