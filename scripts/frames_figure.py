"""Draw docs/conventions-frames.png: the project's frames beside those of the tools it converts to.

Left: the axial plane of a frontal C-arm seen from the feet: the patient's world (DICOM LPS)
and RAS (NIfTI, 3D Slicer, DiffDRR's world), the source and detector, the detector direction d,
the image axes u (columns) and v (rows), the pinhole camera (OpenCV, DeepDRR: x = -u, y = v,
z = d) and DiffDRR's camera (x = u, y = -v, z = d). Right: the image as stored. Positions and
directions come from :class:`registration.core.geometry.CArm`.

    python scripts/frames_figure.py [out.png]
"""

from __future__ import annotations

import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from registration.core.geometry import CArm

OUT = Path(__file__).resolve().parents[1] / "docs" / "conventions-frames.png"


def _arrow(ax, origin, vector, color, label, *, offset=(0.0, 0.0)) -> None:
    o, v = np.asarray(origin, float), np.asarray(vector, float)
    ax.annotate("", xy=o + v, xytext=o, arrowprops={"arrowstyle": "-|>", "color": color, "lw": 2})
    ax.text(*(o + 1.08 * v + np.asarray(offset)), label, color=color, fontsize=9, ha="center", va="center")


def _out_of_page(ax, at, color, label, toward_viewer: bool) -> None:
    ax.scatter(*at, s=160, facecolors="white", edgecolors=color, linewidths=2, zorder=3)
    ax.scatter(*at, s=40 if toward_viewer else 90, marker="o" if toward_viewer else "x", color=color, zorder=4)
    ax.text(at[0] + 45, at[1], label, color=color, fontsize=9, va="center")


def _axial(ax, carm: CArm) -> None:
    """The axial plane seen from the feet, the radiological way: patient's left on the right
    of the page, anterior up; page (right, up) = world (+x, -y); +z (head) points into the page."""

    def page(p):  # world (x, y, z) -> page (x, -y)
        return np.array([p[0], -p[1]])

    ax.add_patch(plt.Circle((0, 0), 90, color="0.85"))
    ax.text(0, 0, "head", ha="center", va="center", fontsize=9)
    ax.add_patch(plt.Rectangle((-250, -115), 500, 18, color="0.6"))
    ax.text(260, -106, "table", fontsize=8, va="center")
    src, det = page(carm.source_mm), page(carm.detector_center_mm)
    ax.plot(*np.c_[src, det], color="0.6", ls="--", lw=1)
    half = carm.cols * carm.pixel_mm[1] / 2
    ax.plot([det[0] - half, det[0] + half], [det[1], det[1]], color="k", lw=5)
    ax.text(det[0] - half - 20, det[1] + 35, "detector", fontsize=9, ha="right")
    ax.scatter(*src, color="k", s=40)
    ax.text(src[0] + 30, src[1] + 30, "source", fontsize=9)
    _arrow(ax, (0, 0), 220 * page(np.eye(3)[0]), "tab:blue", "+x Left (LPS)", offset=(0, 25))
    _arrow(ax, (0, 0), 220 * page(np.eye(3)[1]), "tab:blue", "+y Posterior", offset=(70, 0))
    _arrow(ax, (0, 0), -220 * page(np.eye(3)[0]), "tab:orange", "+x Right (RAS)", offset=(0, 25))
    _arrow(ax, (0, 0), -220 * page(np.eye(3)[1]), "tab:orange", "+y Anterior", offset=(-75, 0))
    _out_of_page(ax, (-440, -330), "tab:blue", "+z Superior: into the page", toward_viewer=False)
    _arrow(ax, det + [0, 40], 180 * page(carm.u), "tab:green", "u: image columns", offset=(0, 28))
    _arrow(ax, src, 170 * page(carm.direction), "tab:red", "d, camera z", offset=(95, 0))
    _arrow(ax, src, -150 * page(carm.u), "tab:purple", "pinhole x = -u", offset=(-40, -30))
    _arrow(ax, src, 150 * page(carm.u), "tab:brown", "DiffDRR x = u", offset=(40, -30))
    _out_of_page(ax, (-440, -400), "tab:green", "v (rows), pinhole y: toward the feet", toward_viewer=True)
    _out_of_page(ax, (-440, -470), "tab:brown", "DiffDRR y = -v: toward the head", toward_viewer=False)
    ax.set_xlim(-470, 450)
    ax.set_ylim(-900, 560)
    ax.set_aspect("equal")
    ax.axis("off")
    ax.set_title("frontal C-arm (primary 0, secondary 0), axial plane seen from the feet", fontsize=10)


def _image(ax, carm: CArm) -> None:
    ax.add_patch(plt.Rectangle((0, 0), carm.cols, carm.rows, fill=False, lw=2))
    ax.add_patch(plt.Circle((carm.cols / 2, carm.rows / 2), carm.rows * 0.47, color="0.9"))
    ax.set_xlim(-90, carm.cols + 60)
    ax.set_ylim(carm.rows + 60, -80)
    ax.set_aspect("equal")
    ax.axis("off")
    _arrow(ax, (0, -20), (180, 0), "tab:green", "column index: along u", offset=(60, -22))
    _arrow(ax, (-20, 0), (0, 180), "tab:green", "row index:\nalong v", offset=(-25, 60))
    cx, cy = (carm.cols - 1) / 2, (carm.rows - 1) / 2
    ax.scatter([cx], [cy], color="tab:red", s=30)
    ax.text(cx + 10, cy - 14, "central ray: pixel ((cols-1)/2, (rows-1)/2)", fontsize=8, color="tab:red")
    ax.text(carm.cols / 2, carm.rows * 0.15, "head", ha="center", fontsize=9)
    ax.text(carm.cols * 0.1, carm.rows / 2, "patient's\nright", ha="center", fontsize=9)
    ax.text(carm.cols * 0.9, carm.rows / 2, "patient's\nleft", ha="center", fontsize=9)
    ax.text(carm.cols / 2, carm.rows * 0.88, "feet", ha="center", fontsize=9)
    ax.set_title("the frontal image as stored and shown (radiological view)", fontsize=10)


def main(out: Path = OUT) -> Path:
    carm = CArm(rows=512, cols=512)
    fig, (left, right) = plt.subplots(1, 2, figsize=(12, 6.5), gridspec_kw={"width_ratios": [1.25, 1]})
    _axial(left, carm)
    _image(right, carm)
    fig.text(
        0.5,
        0.03,
        "Patient motion M: anatomy the volume shows at X is at M @ X in the image (LPS mm). ITK transform files hold "
        "inv(M), in LPS (fixed = the patient as imaged, moving = the volume); 3D Slicer shows them in RAS.",
        ha="center",
        fontsize=9,
        wrap=True,
    )
    fig.tight_layout(rect=(0, 0.06, 1, 1))
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=100)
    plt.close(fig)
    return out


if __name__ == "__main__":
    print(main(Path(sys.argv[1]) if len(sys.argv) > 1 else OUT))
