"""One recipe for "which 3DRA": its cache key is the one its builder writes; the run's images."""

from __future__ import annotations

import numpy as np
import pytest

import registration.io.cache as cache
import registration.sim.phantom as phantom
from registration.sim.rotational_run import RunRecipe, RunStopped, view_seed
from registration.sim.threedra import VOLUME_SOURCES, VolumeRecipe


@pytest.fixture()
def written(monkeypatch) -> list[tuple[str, dict]]:
    """Every cache entry a builder asks for, answered with a zero volume (nothing is built)."""
    seen: list[tuple[str, dict]] = []

    def fake(kind: str, params: dict, build, *, enabled: bool = True) -> dict:
        seen.append((kind, params))
        return {"data": np.zeros((8, 8, 8), np.float32), "index_to_world": np.eye(4)}

    monkeypatch.setattr(cache, "cached_arrays", fake)
    monkeypatch.setattr(phantom, "cached_arrays", fake)  # imported by name there
    return seen


@pytest.mark.parametrize(
    "recipe",
    [
        VolumeRecipe(volume_format_cm=22.0, voxels=24),
        VolumeRecipe(volume_format_cm=22.0, voxels=24, contrast=False, phantom_seed=3),
        VolumeRecipe(volume_format_cm=22.0, voxels=24, source="resampled", noise_seed=5),
        VolumeRecipe(volume_format_cm=22.0, voxels=24, center_mm=(0.0, -20.0, -40.0)),
        VolumeRecipe(volume_format_cm=22.0, voxels=24, source="resampled", center_mm=(0.0, -20.0, -40.0)),
    ],
)
def test_the_cache_key_is_the_builders(recipe: VolumeRecipe, written: list) -> None:
    recipe.build()
    assert written == [recipe.cache_entry()]  # so is_cached() tells the truth about build()


def test_bad_recipes_are_refused_with_the_reason() -> None:
    assert VOLUME_SOURCES == ("fdk", "resampled")
    with pytest.raises(ValueError, match="volume source must be one of"):
        VolumeRecipe(source="cone-beam")
    with pytest.raises(ValueError, match="full phantom"):
        VolumeRecipe(facial=False)
    with pytest.raises(ValueError, match="voxels"):
        VolumeRecipe(voxels=4)
    with pytest.raises(ValueError, match="volume_format_cm"):
        VolumeRecipe(volume_format_cm=float("nan"))
    assert VolumeRecipe(volume_format_cm=27) == VolumeRecipe(volume_format_cm=27.0)  # one recipe, one key


def test_run_recipe_images_are_cached_and_stoppable(monkeypatch, tmp_path) -> None:
    monkeypatch.setenv("ROADMAP3D_CACHE", str(tmp_path))
    recipe = RunRecipe(projections=3, arc_deg=200.0, pixels=16, supersample=1)
    assert not recipe.is_cached()
    calls: list[tuple[int, int]] = []
    with pytest.raises(RunStopped):
        recipe.images(progress=lambda done, total: calls.append((done, total)) or done == 2)
    assert calls == [(1, 3), (2, 3)] and not recipe.is_cached()  # nothing half-written
    images, masks = recipe.images()
    assert images.shape == (3, 16, 16) and masks.shape == (3, 16, 16) and masks.dtype == bool
    assert recipe.is_cached() and float(images[masks].max()) > 0.5  # the head attenuates
    again, _ = recipe.images(progress=lambda *_: pytest.fail("a cached run is not simulated again"))
    np.testing.assert_array_equal(again, images)
    assert view_seed(0, 7) == 7 and view_seed(2, 1) == 200007  # the one seed formula of every run
    np.testing.assert_allclose(recipe.angles(), [-100.0, 0.0, 100.0])
