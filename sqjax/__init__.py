"""sqjax: direct part-level segmentation of range images with superquadrics, in JAX."""

from importlib.metadata import PackageNotFoundError, version

from . import rotation as rotation
from .superquadric import Superquadric as Superquadric
from .superquadric import contains as contains
from .superquadric import distance as distance
from .superquadric import inside_outside as inside_outside
from .superquadric import radial_distance as radial_distance
from .superquadric import residual as residual
from .superquadric import sample_surface as sample_surface
from .superquadric import to_trimesh as to_trimesh

try:
    __version__ = version("sqjax")
except PackageNotFoundError:  # pragma: no cover - running from a source tree
    __version__ = "0.0.0"
