"""sqjax: direct part-level segmentation of range images with superquadrics, in JAX.

The public API is the names below, after the paper's ideas; everything else lives in submodules named
after them (`sqjax.scenes`, `sqjax.evaluate`, `sqjax.mesh`, `sqjax.plot`, ...), which `sqjax.<name>`
imports on first use. Names are imported on first use too (PEP 562), so `import sqjax` and the
command line's `--help` do not import JAX.
"""

from importlib import import_module
from importlib.metadata import PackageNotFoundError, version
from importlib.util import find_spec

_NAMES = {
    # the superquadric: inside-outside function (eq. 5), size-weighted residual (eq. 7), distance (eq. 10)
    "Superquadric": "superquadric",
    "inside_outside": "superquadric",
    "residual": "superquadric",
    "distance": "superquadric",
    # recovery of one superquadric (Solina & Bajcsy), batched
    "fit": "fitting",
    "FitOptions": "fitting",
    # recover-and-select
    "segment": "segmentation",
    "Segmentation": "segmentation",
    "SegmentOptions": "options",
    # model selection: maximise m^T Q m
    "select": "selection",
    "build_q": "selection",
    "SelectionWeights": "selection",
    # range images and files
    "RangeImage": "rangeimage",
    "PinholeCamera": "rangeimage",
    "read_range_image": "formats",
    "read_points": "formats",
    "read_segmentation": "export",
    "write_segmentation": "export",
    # scores, many scenes, start-up
    "hoover": "evaluate",
    "segment_many": "dataset",
    "enable_compilation_cache": "cache",
}

__all__ = sorted(_NAMES)  # pyright: ignore[reportUnsupportedDunderAll]  (the lazy names)

try:
    __version__ = version("sqjax")
except PackageNotFoundError:  # pragma: no cover - running from a source tree
    __version__ = "0.0.0"


def __getattr__(name: str):
    if name in _NAMES:
        value = getattr(import_module(f".{_NAMES[name]}", __name__), name)
    elif not name.startswith("_") and find_spec(f"{__name__}.{name}") is not None:
        value = import_module(f".{name}", __name__)
    else:
        raise AttributeError(f"module 'sqjax' has no attribute {name!r}")
    globals()[name] = value  # later look-ups skip this function
    return value


def __dir__():
    return sorted({*globals(), *__all__})
