"""The app assesses an estimate as ``register --confidence`` does, one view's far look included:
at the depth correction's level of the registration's own renderer."""

from __future__ import annotations

import pytest

from app.web.gui import RoadmapApp


def test_the_app_looks_far_along_the_beam_at_the_registrations_level(
    fresh: RoadmapApp, monkeypatch: pytest.MonkeyPatch
) -> None:
    import registration.core.assess as assess_module
    from registration.core.depth import scan_level

    seen: list[dict] = []
    real = assess_module.assess_on

    def spy(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
        seen.append(kwargs)
        return real(*args, **kwargs)

    monkeypatch.setattr(assess_module, "assess_on", spy)
    fresh.register_button.value = True
    assert fresh.session.wait(120), "registration did not finish"
    assert len(seen) == 1, seen
    s = fresh.session
    assert seen[0]["far_level"] == scan_level(s.data.renderer(s.settings.volume_format_cm))
    assessment = s.run.assessment
    assert assessment is not None and assessment["applied"], assessment
    assert "depth_far" not in assessment  # the phantom at rest: a sharp peak, no look
