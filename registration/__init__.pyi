# Type information for the lazily loaded public API (registration/__init__.py).
from registration.api import Assessment as Assessment
from registration.api import CArm as CArm
from registration.api import Example as Example
from registration.api import Preparation as Preparation
from registration.api import Volume as Volume
from registration.api import XRayImage as XRayImage
from registration.api import assess as assess
from registration.api import estimate_geometry as estimate_geometry
from registration.api import load_example as load_example
from registration.api import register as register
from registration.api import render_drr as render_drr
from registration.api import residuals as residuals
from registration.api import track as track

__version__: str
__all__: list[str]
