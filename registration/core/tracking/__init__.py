"""Live motion compensation over a fluoroscopy run (CONVENTIONS §7).

Per frame, the engine compares the frame with a DRR at the **last applied pose** (the pose the
roadmap shows). The measure (gradient difference, on a small copy of the frame) has a level
that it keeps on the frames of a still patient, with a frame-to-frame noise the tracker
learns; a drop of more than ``detect_sigmas`` noise units (and more than ``detect_relative``
of the level) means the patient moved:

- a small drop is **refined** from the last applied pose: a few Newton steps on each
  parameter from central differences (the probes of one step render side by side on the
  cores), a cheap single level;
- a large drop, or a refinement that does not bring the measure back to its level, runs the
  **full capture** (:func:`registration.core.register.register`, capture runs and polish) from
  the last applied pose, then the same refinement at the tracking level.

Every estimate is assessed (:mod:`registration.core.confidence`: the level the measure
recovered, its margin over perturbed poses, the capture runs' agreement, the field's edges,
the planes' agreement) and ``applied`` or ``withheld``; a withheld estimate keeps the last
applied pose and says why. Frames with no detected motion are ``unchanged``.

:func:`track_run` replays a run at its frame times: a frame that arrives while the engine is
still busy is **skipped**, never queued (the roadmap must follow the newest frame), and counted.
One view searches the paper's five parameters; two views (biplane) all six.

A renderer of prepared levels (:func:`registration.core.prepare.prepare_volume`) holds a crop
of the volume: what the field reaches over one capture's search from the pose it was prepared
at. The tracker keeps the crop's margin for a capture from the applied pose
(:meth:`registration.core.prepare.Crop.margin`, a few 4x4 products when the pose changed) and,
when it falls short, prepares the crop again around the applied pose in a thread of its own
(:func:`registration.core.prepare.recrop`: slices of the same levels), swapped in at the first
frame after it is ready; that frame says so (``reprepared``). A crop of the whole body never is.
"""

from registration.core.tracking.evidence import registration_evidence
from registration.core.tracking.options import PATHS, STATUSES, FrameEstimate, TrackingOptions, light_capture
from registration.core.tracking.run import TrackingRun, track_run
from registration.core.tracking.tracker import Tracker

__all__ = [
    "PATHS",
    "STATUSES",
    "FrameEstimate",
    "Tracker",
    "TrackingOptions",
    "TrackingRun",
    "light_capture",
    "registration_evidence",
    "track_run",
]
