"""The example notebook `examples/pipeline.ipynb` runs end to end (nbclient, a real kernel) and reaches
a simulated grasp: observe -> superquadric fit -> Stage-1 candidates -> E-RNet -> plan -> trial."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

nbclient = pytest.importorskip("nbclient")
nbformat = pytest.importorskip("nbformat")
pytest.importorskip("ipykernel")

from envs.trial import Outcome  # noqa: E402

NOTEBOOK = Path(__file__).resolve().parents[1] / "examples" / "pipeline.ipynb"
MIN_IMAGES = 7  # scene, target cloud, fit, candidates, scores, chosen grasp, trial


def outputs(nb, kind: str) -> list:
    code = [cell for cell in nb.cells if cell.cell_type == "code"]
    return [out for cell in code for out in cell.get("outputs", []) if out.output_type == kind]


def test_notebook_is_saved_without_outputs():
    nb = nbformat.read(NOTEBOOK, as_version=4)
    nbformat.validate(nb)
    code = [cell for cell in nb.cells if cell.cell_type == "code"]
    assert code and all(not cell.outputs and cell.execution_count is None for cell in code)
    # Every import in the first code cell (easy to update when modules move).
    lines = [line.lstrip() for cell in code[1:] for line in cell.source.splitlines()]
    assert [line for line in lines if line.startswith(("import ", "from "))] == []


@pytest.mark.slow
def test_pipeline_notebook_runs_and_simulates_a_grasp(tmp_path):
    nb = nbformat.read(NOTEBOOK, as_version=4)
    resources = {"metadata": {"path": str(tmp_path)}}  # the kernel's working directory
    client = nbclient.NotebookClient(nb, timeout=600, kernel_name="python3", resources=resources)
    client.execute()  # raises CellExecutionError (with the traceback) if any cell fails

    assert outputs(nb, "error") == []
    shown = outputs(nb, "display_data") + outputs(nb, "execute_result")
    images = [out for out in shown if "image/png" in out.get("data", {})]
    assert len(images) >= MIN_IMAGES

    last = [out.text for out in nb.cells[-1].outputs if out.output_type == "stream" and out.name == "stdout"]
    summary = json.loads("".join(last).strip().splitlines()[-1])
    assert summary["fit_valid"] is True
    assert summary["n_candidates"] >= 1 and 1 <= summary["n_scored"] <= summary["n_candidates"]
    assert summary["kind"] in ("evaluated", "refined", None)
    assert 0.0 <= summary["score"] <= 1.0
    assert summary["outcome"] in {o.name.lower() for o in Outcome}
    assert summary["success"] == (summary["outcome"] == "success")
