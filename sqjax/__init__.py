"""sqjax: direct part-level segmentation of range images with superquadrics, in JAX.

The names below are imported on first use (module-level `__getattr__`, PEP 562), so `import sqjax`
and the command line's `--help` do not import JAX; `from sqjax import X` and `sqjax.X` work as usual.
"""

import sys
import types
from importlib import import_module
from importlib.metadata import PackageNotFoundError, version

# public name -> the module that defines it
_NAMES = {
    "HooverScore": "evaluate",
    "explained_fraction": "evaluate",
    "hoover": "evaluate",
    "parameter_errors": "evaluate",
    "volume_iou": "evaluate",
    "volume_iou_batch": "evaluate",
    "label_colors": "export",
    "labels_to_png": "export",
    "parts_to_scene": "export",
    "write_segmentation": "export",
    "read_segmentation": "export",
    "superquadric_from_dict": "export",
    "enable_compilation_cache": "cache",
    "Fit": "fitting",
    "FitOptions": "fitting",
    "fit": "fitting",
    "read_points": "formats",
    "read_range_image": "formats",
    "read_rgbd": "formats",
    "write_points": "formats",
    "write_range_image": "formats",
    "OrthographicCamera": "rangeimage",
    "PinholeCamera": "rangeimage",
    "RangeImage": "rangeimage",
    "figure_sequence": "plot",
    "paper_scene": "scenes",
    "random_scene": "scenes",
    "multipart_scene": "scenes",
    "render": "scenes",
    "Segmentation": "segment",
    "SegmentOptions": "segment",
    "segment": "segment",
    "segment_many": "dataset",
    "SelectionWeights": "selection",
    "Superquadric": "superquadric",
    "contains": "superquadric",
    "distance": "superquadric",
    "inside_outside": "superquadric",
    "radial_distance": "superquadric",
    "residual": "superquadric",
    "signed_distance": "superquadric",
    "sample_surface": "superquadric",
    "to_trimesh": "superquadric",
}
_MODULES = ("evaluate", "plot", "rotation", "scenes")

__all__ = sorted([*_NAMES, *_MODULES])  # pyright: ignore[reportUnsupportedDunderAll]  (the lazy names)

try:
    __version__ = version("sqjax")
except PackageNotFoundError:  # pragma: no cover - running from a source tree
    __version__ = "0.0.0"


def __getattr__(name: str):
    if name in _NAMES:
        value = getattr(import_module(f".{_NAMES[name]}", __name__), name)
    elif name in _MODULES:
        value = import_module(f".{name}", __name__)
    else:
        raise AttributeError(f"module 'sqjax' has no attribute {name!r}")
    globals()[name] = value  # later look-ups skip this function
    return value


def __dir__():
    return sorted({*globals(), *__all__})


class _Package(types.ModuleType):
    """Keeps `sqjax.segment` the function: importing the submodule `sqjax.segment` (which any
    `from sqjax.segment import ...` does) would otherwise bind the module over it, as the eager
    `from .segment import segment` used to undo."""

    def __setattr__(self, name, value):
        if isinstance(value, types.ModuleType) and name in _NAMES and value.__name__ == f"{__name__}.{name}":
            value = getattr(value, name)
        super().__setattr__(name, value)


sys.modules[__name__].__class__ = _Package
