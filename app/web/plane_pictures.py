"""The pictures of one plane the presenter shows: the fluoro tile with the Compare tab's overlay,
the DRR at the estimate, the detector picture for the 3-D scene and the gradient row's inputs;
what depends on the X-ray image alone is computed once per image and size."""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np

from app.web import views
from app.web.layout import Layout
from app.web.session import Session
from registration.core.geometry import CArm
from registration.studies import qa_images

if TYPE_CHECKING:
    from app.web.qa_panel import CompareSettings

#: The fluoro tile's caption when the volume has no vessel surface.
NO_ROADMAP = "no roadmap: no vessels in the volume"
#: The fluoro tile's size in the large single-image layout (pixels).
LARGE_TILE_PX = 768
#: The fluoro tile's caption for each Compare mode (the outline's: with a vessel surface).
CAPTIONS = {
    "outline": "red: roadmap at the estimate",
    "edges": "green: DRR edges at the estimate",
    "checkerboard": "checkerboard: image / DRR at the estimate",
    "difference": "image - DRR at the estimate (gray: agree)",
    "wipe": "left: before (machine-based) | right: registered",
}


class PlanePictures:
    """One plane's pictures for the presenter (``settings``: the Compare tab's settings)."""

    def __init__(self, session: Session, layout: Layout, settings: Callable[[], CompareSettings]) -> None:
        self.session = session
        self.layout = layout
        self.settings = settings
        self._by_image: dict[tuple[int, int, int], tuple[Any, dict[str, np.ndarray]]] = {}

    def tiles(self, xray: Any, size: int | None = None) -> dict[str, np.ndarray]:
        """What depends on the X-ray image only, computed once per image (per plane) and size
        (the display's, or ``size``)."""
        size = self.session.config.display_px if size is None else int(size)
        key = (id(xray), size, id(getattr(self.session.data, "region", None)))  # a new region shades anew
        cached = self._by_image.get(key)
        if cached is not None and cached[0] is xray:
            return cached[1]
        mask_u8 = xray.mask.astype(np.uint8)
        data = self.session.data
        narrow = getattr(data, "region_views", None)  # the user's data: the neck's pixels leave the field too
        used = narrow([xray], None)[0].mask if narrow is not None and xray is data.fixed_xray else xray.mask
        tiles = {
            "fluoro": views.resize(views.to_gray(xray.image, xray.mask), size),
            "mask": views.resize(mask_u8, size).astype(bool),
            "mask_half": views.resize(mask_u8, size // 2).astype(bool),
            "mask_third": views.resize(mask_u8, size // 3).astype(bool),
            "gradient": views.resize(views.gradient_image(xray.image, xray.mask), size),
            "attenuation": views.resize(np.asarray(xray.image, np.float32), size),
            # what the registration uses: the field without the pixels the region leaves out
            "used": views.resize(used.astype(np.uint8), size).astype(bool),
        }
        if len(self._by_image) >= 4:  # plane A and B, each shown and about to be shown
            self._by_image.pop(next(iter(self._by_image)))
        self._by_image[key] = (xray, tiles)
        return tiles

    def plane(
        self, xray: Any, motion: np.ndarray, volume_format: float, *, live: bool, plane: str,
        initial: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:  # fmt: skip
        """One plane's row (fluoro with the Compare tab's overlay | DRR at the estimate; the fluoro
        tile alone in the large layout), its detector picture for the 3-D scene, and what the
        gradient row needs (DRR, its mask). ``initial``: the machine-based pose (before / after)."""
        initial = np.eye(4) if initial is None else initial
        s = self.session
        settings = self.settings()
        size = LARGE_TILE_PX if settings.large else s.config.display_px
        geometry: CArm = xray.geometry
        tiles = self.tiles(xray, size)
        vessels = s.data.meshes(volume_format).get("vessels")
        mode = "outline" if live else settings.mode  # while the optimizer runs: the outline only
        tile_geometry = geometry.resized(size, size)
        thickness = 1 if size <= 400 else 2
        silhouette = None
        if vessels is not None:
            spacing = s.data.mesh_spacing_mm(volume_format)
            silhouette = views.vessel_silhouette(np.asarray(vessels.vertices), motion, tile_geometry, spacing)
        if mode == "outline":
            fluoro = views.gray_rgb(tiles["fluoro"])
            if silhouette is not None:
                views.draw_outline(fluoro, silhouette, thickness=thickness)
        else:
            fluoro = self._compare_tile(mode, tiles, tile_geometry, motion, initial, silhouette, volume_format,
                                        thickness)  # fmt: skip
        if bool(self.layout.show_field.value):  # what the registration leaves out, shaded and outlined
            views.shade_outside(fluoro, tiles["used"])
        if settings.zoom > 1.0:
            fluoro = qa_images.zoomed(fluoro, settings.zoom, settings.pan)
        prefix = f"PLANE {plane}  " if plane else ""
        views.label(fluoro, f"{prefix}{xray.kind.upper()}  {views.angles_text(geometry)}")
        caption = NO_ROADMAP if mode == "outline" and vessels is None else CAPTIONS[mode]
        views.label(fluoro, caption, corner="bottom-left")

        # The DRR thumbnail: coarser while the optimizer runs (it competes for the same cores).
        drr_px = size // 3 if live else size // 2
        drr_mask = tiles["mask_third"] if live else tiles["mask_half"]
        drr = s.data.renderer(volume_format).render(geometry.resized(drr_px, drr_px), motion, level=2 if live else 1)
        if settings.large:  # the fluoro tile alone (the panel is wider)
            return fluoro, views.resize(fluoro, 256), tiles["gradient"], drr, drr_mask
        drr_gray = views.resize(views.to_gray(drr, drr_mask), size)
        drr_gray[~tiles["mask"]] = 0
        drr_tile = views.label(views.gray_rgb(drr_gray), "DRR at the estimate")
        return views.side_by_side(fluoro, drr_tile), views.resize(fluoro, 256), tiles["gradient"], drr, drr_mask

    def _compare_tile(
        self, mode: str, tiles: dict[str, np.ndarray], tile_geometry: CArm, motion: np.ndarray, initial: np.ndarray,
        silhouette: Any, volume_format: float, thickness: int,
    ) -> np.ndarray:  # fmt: skip
        """The fluoro tile in a Compare mode other than the outline: the image against the DRR at the
        estimate (and, for the wipe, at the machine-based pose)."""
        s, settings = self.session, self.settings()
        renderer = s.data.renderer(volume_format)
        vessels = s.data.meshes(volume_format).get("vessels")
        drr_tile = renderer.render(tile_geometry, motion, level=1)
        drr_initial = initial_silhouette = None
        if mode == "wipe":
            drr_initial = renderer.render(tile_geometry, initial, level=1)
            if vessels is not None:
                initial_silhouette = views.vessel_silhouette(
                    np.asarray(vessels.vertices), initial, tile_geometry, s.data.mesh_spacing_mm(volume_format)
                )
        return qa_images.compare(
            mode, image=tiles["attenuation"], drr=drr_tile, mask=tiles["mask"], outline=silhouette,
            drr_initial=drr_initial, outline_initial=initial_silhouette, tile_px=settings.checker_px,
            wipe_fraction=settings.wipe, thickness=thickness,
        )  # fmt: skip
