"""examples/first_session.ipynb runs start to finish, headless (nbclient, the ipykernel of this environment),
and is committed without outputs."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

NOTEBOOK = Path(__file__).resolve().parents[1] / "examples" / "first_session.ipynb"


def test_the_notebook_is_committed_without_outputs():
    cells = json.loads(NOTEBOOK.read_text())["cells"]
    code = [c for c in cells if c["cell_type"] == "code"]
    assert code and all(not c["outputs"] and c["execution_count"] is None for c in code)


def test_the_notebook_runs_start_to_finish(tmp_path, monkeypatch):
    nbformat = pytest.importorskip("nbformat")
    from nbclient import NotebookClient

    monkeypatch.setenv("CONTACT_VIZ_CACHE", str(tmp_path / "cache"))
    notebook = nbformat.read(NOTEBOOK, as_version=4)
    # any error in a cell raises CellExecutionError, naming the cell
    NotebookClient(notebook, timeout=900, kernel_name="python3", resources={"metadata": {"path": str(tmp_path)}}
                   ).execute()
    outputs = [o for c in notebook.cells if c.cell_type == "code" for o in c.outputs]
    kinds = [o.output_type for o in outputs]
    assert "error" not in kinds
    images = [o for o in outputs if "image/png" in o.get("data", {})]
    assert len(images) == 2  # the distance / force / posterior plot and the frame's layers
    widgets = [o for o in outputs if "application/vnd.jupyter.widget-view+json" in o.get("data", {})]
    assert widgets  # rr.notebook_show(): the inline viewer
    text = "".join(o.get("text", "") for o in outputs)
    assert "150 frames in" in text and "in contact: instrument 1 on" in text
    assert (tmp_path / "nb_sessions" / "kidney_9" / "truth.csv").is_file()
