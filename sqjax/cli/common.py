"""What every command shares: the one-line parser, exit codes, argument types, `-o` options, messages.

Imports nothing heavy at module level (`sqjax --help` reads this module): NumPy and sqjax's own
modules are imported when an argument is parsed or a command runs.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable

EXIT_USAGE = 2
"""Bad input: a missing or damaged file, an unsupported format, a bad option."""
EXIT_FAILURE = 1
"""A bug (an internal error), an interrupted pipe, or some inputs of many failed."""


class CLIError(ValueError):
    """A user error with a message fit for one line."""


class Parser(argparse.ArgumentParser):
    """argparse that reports errors in one line: `sqjax: error: ... (see 'sqjax segment --help')`.

    `describe`: a function making the description, called when the help is shown (so that a
    description that needs a heavy module does not import it for every `--help`).
    """

    def __init__(self, *args, describe: Callable[[], str] | None = None, **kwargs):
        super().__init__(*args, **kwargs)
        self.describe = describe

    def error(self, message):
        hint = f" (see '{self.prog} --help')"
        self.exit(EXIT_USAGE, f"sqjax: error: {message}{hint}\n")

    def format_help(self) -> str:
        if self.describe is not None:
            self.description, self.describe = self.describe(), None
        return super().format_help()


def one_line(e: BaseException) -> str:
    """An exception's message on one line; OSErrors without "[Errno N]" and with their file name."""
    msg = str(e) or type(e).__name__
    if isinstance(e, OSError) and e.strerror and e.errno is not None:
        msg = e.strerror  # without the "[Errno N]" prefix; our own messages carry the path in strerror
    if isinstance(e, OSError) and e.filename and str(e.filename) not in msg:
        msg = f"{e.filename}: {msg}"
    return " ".join(msg.split())


API_HINTS = (
    (
        "pass camera=PinholeCamera(...) or OrthographicCamera(...)",
        "pass --camera fx,fy,cx,cy, --intrinsics FILE.json or --ortho PIXEL",
    ),
    ("pass camera=", "pass --camera fx,fy,cx,cy or --intrinsics FILE.json"),
    (
        "is a range image; use read_range_image",
        "is a range image: `sqjax fit` takes a point cloud; segment it with `sqjax segment`",
    ),
)
"""(the library's advice, the command line's): errors of the readers name API arguments."""


def for_command_line(message: str) -> str:
    """An error message with the library's advice (`camera=`, `read_range_image`) said as flags."""
    for api, cli in API_HINTS:
        if api in message:
            return message.replace(api, cli)
    return message


# ----------------------------------------------------------------------------------------------------
# argument types


def _finite(*values) -> bool:
    import numpy as np

    return bool(np.isfinite(values).all())


def _floats(text: str, n: tuple[int, ...], what: str) -> list[float]:
    try:
        vals = [float(v) for v in text.replace(" ", "").split(",")]
    except ValueError:
        vals = []
    if len(vals) not in n or not _finite(*vals):
        raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}")
    return vals


def camera_arg(text: str):
    """`fx,fy,cx,cy` -> a `PinholeCamera`."""
    from ..rangeimage import PinholeCamera

    fx, fy, cx, cy = _floats(text, (4,), "four numbers fx,fy,cx,cy (pixels)")
    try:
        return PinholeCamera(fx, fy, cx, cy)
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None


def ortho_arg(text: str) -> list[float]:
    """`PIXEL[,cx,cy]` -> [pixel_size] or [pixel_size, cx, cy]."""
    vals = _floats(text, (1, 3), "PIXEL or PIXEL,cx,cy (pixel size in depth units)")
    if not vals[0] > 0:
        raise argparse.ArgumentTypeError(f"pixel size must be > 0, got {vals[0]}")
    return vals


def positive(kind):
    """An argument type: a finite `kind` (int or float) > 0."""

    def parse(text):
        try:
            v = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a positive {kind.__name__}, got {text!r}") from None
        if not (_finite(v) and v > 0):
            raise argparse.ArgumentTypeError(f"expected a positive {kind.__name__}, got {text!r}")
        return v

    parse.__name__ = kind.__name__
    return parse


def noise_arg(text: str) -> float:
    """A noise std: a finite number >= 0."""
    try:
        v = float(text)
    except ValueError:
        v = float("nan")
    if not (_finite(v) and v >= 0):
        raise argparse.ArgumentTypeError(f"noise must be a finite number >= 0, got {text!r}")
    return v


def depth_scale_arg(text: str) -> float:
    """Stored depth units per metre (`formats.check_depth_scale`), with a hint for the old convention."""
    from ..formats import check_depth_scale

    try:
        return check_depth_scale(float(text), "--depth-scale")
    except ValueError as e:
        raise argparse.ArgumentTypeError(
            str(e) if "convention" in str(e) else f"expected a positive number (depth units per metre), got {text!r}"
        ) from None


def shape_arg(text: str) -> tuple[int, int]:
    """`H,W` (or `HxW`), at least 8 x 8."""
    try:
        h, w = (int(v) for v in text.lower().replace("x", ",").split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected H,W, got {text!r}") from None
    if h < 8 or w < 8:
        raise argparse.ArgumentTypeError(f"image shape must be at least 8x8, got {h}x{w}")
    return h, w


def tolerance_arg(text: str) -> float:
    """Hoover et al.'s overlap tolerance T in (0, 1], as `sqjax.hoover` takes it (its matching is one to
    one at every T; the benchmarks report T = 0.8 and 0.5)."""
    try:
        t = float(text)
    except ValueError:
        t = float("nan")
    if not 0.0 < t <= 1.0:
        raise argparse.ArgumentTypeError(f"tolerance must be in (0, 1], got {text!r}")
    return t


# ----------------------------------------------------------------------------------------------------
# segment options


def segment_options(pairs, noise):
    """`-o KEY=VALUE` pairs -> `SegmentOptions` (`SegmentOptions.parse` gives each value its type)."""
    from ..options import SegmentOptions

    kw = {}
    for pair in pairs or ():
        key, sep, text = pair.partition("=")
        if not sep:
            # -o is a segment option here, where many tools take it for the output: say where that goes
            raise CLIError(
                f"bad segment option {pair!r}: expected KEY=VALUE (-o sets an option; the output folder is --out DIR)"
            )
        try:
            key, v = SegmentOptions.parse(key, text)
        except ValueError as e:
            raise CLIError(str(e)) from None
        if isinstance(v, (int, float)) and not isinstance(v, bool) and not (_finite(v) and v >= 0):
            # no SegmentOptions number is negative or infinite (SegmentOptions checks the exact ranges)
            raise CLIError(f"bad value for segment option {key}: {text.strip()!r} (must be a finite number >= 0)")
        kw[key] = v
    if noise is not None:
        kw["noise"] = noise
    try:
        return SegmentOptions.create(**kw)
    except (TypeError, ValueError) as e:  # the options' own checks name the field
        given = ", ".join(f"{k}={v!r}" for k, v in kw.items()) or "defaults"
        raise CLIError(f"bad segment options ({given}): {one_line(e)}") from None
