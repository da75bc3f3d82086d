"""The licenses of the installed dependency set: no copyleft dependency slips in unnoticed.

The set is what ``pip install -e ".[test]"`` brings: pyproject.toml's dependencies and its
``test`` extra, followed through each installed distribution's own requirements. A license is
read from the distribution's metadata (License-Expression, License, the classifiers); one that
names a copyleft family fails the test unless :data:`ALLOWED` names the distribution with the
reason it is acceptable. Optional extras that carry a copyleft license (``gpl-jpeg``) are not in
the set: a user adds them on purpose.
"""

from __future__ import annotations

import re
import tomllib
from importlib.metadata import PackageNotFoundError, distribution
from pathlib import Path

import pytest
from packaging.requirements import Requirement
from packaging.utils import canonicalize_name

ROOT = Path(__file__).resolve().parents[1]

#: Copyleft license families, as they appear in expressions, free text and classifiers.
COPYLEFT = re.compile(
    r"\b(A?GPL|LGPL|GNU|MPL|Mozilla Public|EPL|Eclipse Public|CDDL|EUPL|OSL|CECILL|CC-BY-SA|copyleft)",
    re.IGNORECASE,
)

#: Copyleft-licensed dependencies accepted, with why. MPL-2.0 is file-level copyleft: it binds
#: changes to the MPL files themselves, which roadmap3d uses unmodified, and is compatible with
#: Apache-2.0.
ALLOWED = {
    "certifi": "MPL-2.0: Mozilla's CA bundle, used unmodified as data (via requests)",
    "tqdm": "MPL-2.0 AND MIT: progress bars, used unmodified",
    "hypothesis": "MPL-2.0: a test-only dependency, used unmodified, never shipped with the software",
    "pathspec": "MPL-2.0: used by mkdocs to build the documentation (test extra), unmodified, never shipped",
}


def _dependency_names() -> set[str]:
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    todo = [Requirement(r) for r in project["dependencies"] + project["optional-dependencies"]["test"]]
    seen: set[str] = set()
    while todo:
        req = todo.pop()
        name = canonicalize_name(req.name)
        if name in seen or (req.marker is not None and not req.marker.evaluate({"extra": ""})):
            continue
        try:
            dist = distribution(req.name)
        except PackageNotFoundError:
            continue  # an optional requirement of a dependency that is not installed
        seen.add(name)
        for text in dist.requires or []:
            sub = Requirement(text)
            if sub.marker is None or any(sub.marker.evaluate({"extra": e}) for e in ("", *req.extras)):
                todo.append(sub)
    return seen


def license_text(name: str) -> str:
    """Everything the distribution's metadata says about its license, on one line."""
    meta = distribution(name).metadata
    parts = [meta.get("License-Expression") or ""]
    free = meta.get("License") or ""
    parts.append(free if len(free) < 200 else free[:200])  # some paste the whole license: its title is enough
    parts += [c for c in meta.get_all("Classifier") or [] if c.startswith("License ::")]
    return " | ".join(p.replace("\n", " ") for p in parts if p)


def is_copyleft(text: str) -> bool:
    return bool(COPYLEFT.search(text))


@pytest.mark.parametrize(
    ("text", "copyleft"),
    [
        ("GPL V3.0 | License :: OSI Approved :: GNU General Public License v3 (GPLv3)", True),
        ("LGPL-2.1-or-later", True),
        ("AGPL-3.0-only", True),
        ("MPL-2.0 AND MIT", True),
        ("MIT | License :: OSI Approved :: MIT License", False),
        ("BSD-3-Clause", False),
        ("Apache-2.0 OR BSD-2-Clause", False),
        ("Apache 2.0 | License :: OSI Approved :: Apache Software License", False),
    ],
)
def test_copyleft_is_recognised(text: str, copyleft: bool) -> None:
    assert is_copyleft(text) is copyleft


def test_no_copyleft_dependency_outside_the_allow_list() -> None:
    names = _dependency_names()
    # the closure is real: the engine's direct dependencies and their own (numpy via scipy, ...)
    assert {"numpy", "scipy", "pydicom", "python-gdcm", "pytest"} <= names
    assert "pylibjpeg-libjpeg" not in names, "the GPL JPEG plugin must stay an optional extra"
    found = {n: license_text(n) for n in sorted(names)}
    bad = [f"{n}: {t}" for n, t in found.items() if is_copyleft(t) and n not in ALLOWED]
    assert not bad, "copyleft dependencies (add a reason to ALLOWED only after review):\n" + "\n".join(bad)


def test_gpl_jpeg_plugin_is_only_an_optional_extra() -> None:
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    assert not any(Requirement(r).name == "pylibjpeg-libjpeg" for r in project["dependencies"])
    assert any(Requirement(r).name == "pylibjpeg-libjpeg" for r in project["optional-dependencies"]["gpl-jpeg"])
