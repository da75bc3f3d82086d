"""The documentation: the site builds without a warning, the README stays a front page.

``mkdocs build --strict`` fails on any warning (a broken link, a missing anchor, an API
reference that does not resolve); it skips with a message where mkdocs is not installed (it is
in the ``test`` extra). The README keeps the exact test command that .ci/run runs.
"""

from __future__ import annotations

import importlib.util
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def test_readme_is_a_front_page_with_the_ci_command() -> None:
    readme = (ROOT / "README.md").read_text()
    assert len(readme.splitlines()) <= 250, "the README is a front page: details belong in docs/"
    ci = (ROOT / ".ci" / "run").read_text()
    command = next(line for line in ci.splitlines() if line.startswith("python3 -m venv .venv &&"))
    assert command in readme, f"the README must show the test command .ci/run runs: {command}"
    for page in ("docs/getting-started.md", "docs/validation/index.md", "docs/conventions.md"):
        assert page in readme and (ROOT / page).is_file()


@pytest.mark.slow
def test_site_builds_without_warnings(tmp_path: Path) -> None:
    if importlib.util.find_spec("mkdocs") is None:
        pytest.skip("mkdocs is not installed (pip install -e '.[test]' -c constraints.txt)")
    env = {**os.environ, "NO_MKDOCS_2_WARNING": "1"}
    done = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(tmp_path / "site")],
        cwd=ROOT, env=env, capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    log = done.stdout + done.stderr
    warnings = [line for line in log.splitlines() if "WARNING" in line]
    assert done.returncode == 0 and not warnings, log[-4000:]
    api = (tmp_path / "site" / "api" / "index.html").read_text()
    assert "from_array" in api and "load_example" in api  # the reference was generated from the code
