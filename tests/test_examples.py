"""Every example notebook in examples/ runs (each is a jupytext percent-format script).

Each is turned into a notebook (jupytext) and executed by a Jupyter kernel (nbclient), cell by
cell, top to bottom, with a non-interactive matplotlib backend; each ends with asserts on its own
numbers (a registration that fails makes its example fail). They are left out of the default
run; ``pytest -m examples`` runs them (CI does, in a step of its own), and the executed
notebooks are kept beside the test's temporary folder.
"""

from __future__ import annotations

from pathlib import Path

import pytest

EXAMPLES = sorted((Path(__file__).resolve().parents[1] / "examples").glob("[0-9]*.py"))


def test_there_are_examples() -> None:
    assert len(EXAMPLES) >= 5, [p.name for p in EXAMPLES]
    for path in EXAMPLES:
        assert path.read_text().startswith("# %% [markdown]"), f"{path.name} is not a percent-format notebook"


@pytest.mark.slow
@pytest.mark.examples
@pytest.mark.parametrize("path", EXAMPLES, ids=[p.stem for p in EXAMPLES])
def test_example_runs(path: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import jupytext
    import nbformat
    from nbclient import NotebookClient
    from nbclient.exceptions import CellExecutionError

    monkeypatch.setenv("MPLBACKEND", "Agg")  # the kernel inherits it: figures drawn, no window
    notebook = jupytext.read(path)
    client = NotebookClient(
        notebook, timeout=600, kernel_name="python3", resources={"metadata": {"path": str(tmp_path)}}
    )
    try:
        client.execute()
    except CellExecutionError as exc:
        pytest.fail(f"{path.name} failed in a cell:\n{str(exc)[-4000:]}")
    finally:
        nbformat.write(notebook, tmp_path / f"{path.stem}.ipynb")
    code = [c for c in notebook.cells if c.cell_type == "code"]
    assert code and all(c.get("execution_count") for c in code), "a cell did not run"
    assert not [o for c in code for o in c.outputs if o.get("output_type") == "error"]
