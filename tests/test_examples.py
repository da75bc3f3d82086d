"""Every example notebook in examples/ runs (each is a jupytext percent-format script).

They run as plain Python in a fresh process with a non-interactive matplotlib backend, exactly
the cells a notebook would run, top to bottom; each ends with asserts on its own numbers (a
registration that fails makes its example fail). Select them with ``pytest -m examples``.
"""

from __future__ import annotations

import os
import subprocess
import sys
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
def test_example_runs(path: Path, tmp_path: Path) -> None:
    env = {**os.environ, "MPLBACKEND": "Agg"}
    done = subprocess.run(
        [sys.executable, str(path)], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=600
    )
    assert done.returncode == 0, f"{path.name} failed:\n{done.stdout[-2000:]}\n{done.stderr[-4000:]}"
