"""sqjax: direct part-level segmentation of range images with superquadrics, in JAX."""

from importlib.metadata import PackageNotFoundError, version

from . import evaluate as evaluate
from . import plot as plot
from . import rotation as rotation
from . import scenes as scenes
from .dataset import segment_many as segment_many
from .evaluate import HooverScore as HooverScore
from .evaluate import explained_fraction as explained_fraction
from .evaluate import hoover as hoover
from .evaluate import parameter_errors as parameter_errors
from .evaluate import volume_iou as volume_iou
from .evaluate import volume_iou_batch as volume_iou_batch
from .export import label_colors as label_colors
from .export import labels_to_png as labels_to_png
from .export import parts_to_scene as parts_to_scene
from .export import write_segmentation as write_segmentation
from .fitting import Fit as Fit
from .fitting import FitOptions as FitOptions
from .fitting import fit as fit
from .formats import read_points as read_points
from .formats import read_range_image as read_range_image
from .formats import write_points as write_points
from .formats import write_range_image as write_range_image
from .rangeimage import OrthographicCamera as OrthographicCamera
from .rangeimage import PinholeCamera as PinholeCamera
from .rangeimage import RangeImage as RangeImage
from .plot import figure_sequence as figure_sequence
from .scenes import paper_scene as paper_scene
from .scenes import random_scene as random_scene
from .scenes import render as render
from .segment import Segmentation as Segmentation
from .segment import SegmentOptions as SegmentOptions
from .segment import segment as segment
from .selection import SelectionWeights as SelectionWeights
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
