"""Every notebook in notebooks/ runs top to bottom (tiny resolution), so none rots."""
import glob
import os

import nbformat
import pytest
from nbclient import NotebookClient

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
NOTEBOOKS = sorted(glob.glob(os.path.join(ROOT, "notebooks", "*.ipynb")))


@pytest.mark.parametrize("path", NOTEBOOKS, ids=os.path.basename)
def test_notebook_runs(path, tmp_path, monkeypatch):
    monkeypatch.setenv("NB_RES", "16")
    monkeypatch.setenv("NB_REF_SPP", "64")
    monkeypatch.setenv("MI_TWOPASS_ROOT", ROOT)
    monkeypatch.setenv("MI_TWOPASS_CACHE", str(tmp_path / "refs"))
    monkeypatch.setenv("MPLBACKEND", "Agg")
    nb = nbformat.read(path, as_version=4)
    NotebookClient(nb, timeout=300, kernel_name="python3",
                   resources={"metadata": {"path": os.path.dirname(path)}}).execute()
    outputs = [o for c in nb.cells if c.cell_type == "code" for o in c.get("outputs", [])]
    assert not [o for o in outputs if o.get("output_type") == "error"]
    text = "".join(o.get("text", "") for o in outputs)
    assert "relMSE" in text  # the comparison ran and printed its numbers


def test_there_is_a_notebook():
    assert NOTEBOOKS
