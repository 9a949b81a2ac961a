"""The notebooks in notebooks/: committed without outputs, and they run end to end on a tiny checkpoint.

The slow test trains a checkpoint through ``python -m src.train`` (the tiny settings of
test_train_entry) and executes every notebook on it in a fresh kernel; executed copies stay in
memory, the files in notebooks/ are never written.
"""

from __future__ import annotations

from pathlib import Path

import nbformat
import pytest

REPO = Path(__file__).resolve().parents[1]
NOTEBOOKS = [REPO / "notebooks" / "walkthrough.ipynb", REPO / "notebooks" / "visualize_predictions.ipynb"]


@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.name)
def test_notebooks_are_committed_without_outputs(path):
    nb = nbformat.read(path, as_version=4)
    nbformat.validate(nb)
    assert nb.metadata.kernelspec.name == "python3"
    code = [cell for cell in nb.cells if cell.cell_type == "code"]
    assert code, f"{path.name} has no code cells"
    for i, cell in enumerate(nb.cells):
        if cell.cell_type == "code":
            assert cell.outputs == [], f"{path.name}: cell {i} has outputs (strip them before committing)"
            assert cell.execution_count is None, f"{path.name}: cell {i} has an execution count"


@pytest.fixture
def tiny_checkpoint(tiny_run) -> Path:
    """The checkpoint of the session's tiny run (conftest.tiny_run)."""
    return tiny_run / "checkpoints" / "last.ckpt"


@pytest.mark.slow
def test_notebooks_run_on_a_trained_checkpoint(tiny_checkpoint, monkeypatch):
    from nbclient import NotebookClient

    monkeypatch.setenv("I2S_CHECKPOINT", str(tiny_checkpoint))  # the kernel inherits the environment
    monkeypatch.setenv("OMP_NUM_THREADS", "2")
    for path in NOTEBOOKS:
        nb = nbformat.read(path, as_version=4)  # executed in memory only
        client = NotebookClient(
            nb, timeout=300, kernel_name="python3", allow_errors=False, resources={"metadata": {"path": str(REPO)}}
        )
        client.execute()  # raises CellExecutionError, naming the cell, on the first error
        outputs = [out for cell in nb.cells if cell.cell_type == "code" for out in cell.outputs]
        errors = [out for out in outputs if out.output_type == "error"]
        assert not errors, f"{path.name}: {[(e.ename, e.evalue) for e in errors]}"
        assert all(cell.execution_count for cell in nb.cells if cell.cell_type == "code"), f"{path.name}: not all ran"
        images = [out for out in outputs if out.output_type == "display_data" and "image/png" in out.get("data", {})]
        assert images, f"{path.name} displayed no image"
        text = "".join(out.get("text", "") for out in outputs if out.output_type == "stream")
        assert str(tiny_checkpoint) in text, f"{path.name} did not use I2S_CHECKPOINT"
    for path in NOTEBOOKS:
        assert not any(c.get("outputs") for c in nbformat.read(path, as_version=4).cells), f"{path} was written"
