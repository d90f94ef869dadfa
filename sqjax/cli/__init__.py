"""The `sqjax` command line: segment range images and point clouds, fit one superquadric, render and score.

Commands (each has `--help`)::

    sqjax demo     [--out DIR]                          a generated scene (Fig. 3 of the paper), no download
    sqjax segment  INPUT [--camera fx,fy,cx,cy | --ortho PIXEL[,cx,cy] | --intrinsics FILE.json]
                   [--color IMAGE] [--depth-scale S] [--subsample STEP] [--noise SIGMA]
                   [-o KEY=VALUE ...] [--out DIR]
    sqjax render   SCENE --out FILE                     SCENE: a paper scene name or random:SEED
    sqjax evaluate RESULT TRUTH [--tolerance 0.8] [--json OUT]
    sqjax fit      POINTS [--json OUT]

`segment` reads range images (`.npz`, `.npy`, 16-bit `.png`, organised `.pcd`) and point clouds
(`.ply`, `.xyz`, `.txt`, `.csv`, unorganised `.pcd`, `(N, 3)` `.npy`, mesh vertices of `.obj` / `.stl`) and
writes into DIR: `models.json` (schema: `sqjax.export`), `labels.npy` (raw int32 labels, 0 = none,
i + 1 = part i), `labels.png` (colour labels) and `labels_id.png` (16-bit label ids; clouds:
`labels.ply`, coloured points), `parts.glb` (glTF, Y-up) and `parts.ply` (camera frame) part meshes
coloured as the labels, and `figure.png` (the paper's panel sequence). RGB-D frames: a 16-bit depth
PNG with `--intrinsics cam.json --depth-scale 1000 [--color rgb.png]`. `--depth-scale` is stored units
per metre and divides (Open3D's convention; values below 1, the old multiplying form, are refused).

Outputs are checked writable before any work, written into a temporary folder and renamed into place
(a failed run leaves no partial file; symlinks in DIR are replaced, never followed). The compiled
kernels are cached on disk (`$XDG_CACHE_HOME/sqjax/jax`, `~/.cache/sqjax/jax` or `$SQJAX_CACHE_DIR`);
`--no-cache` or `SQJAX_NO_CACHE=1` turn that off.

`fit` writes (`--json`) one JSON object, schema version 1::

    {"version": 1, "sqjax_version": str, "input": str,
     "size": [a1, a2, a3],               # half-axes, units of the points
     "epsilon": [e1, e2],                # shape exponents
     "rotation": [[3 x 3]],              # columns = model axes in the points' frame
     "euler_zyz": [phi, theta, psi],     # rad, R = Rz(phi) Ry(theta) Rz(psi)
     "translation": [x, y, z],           # centre
     "taper": [Kx, Ky], "bend": [k, alpha],   # zero unless --deform
     "cost": float,                      # G = sum of squared residuals (FitOptions.residual: the
                                         # points' distances to the surface by default)
     "converged": bool, "num_points": int,
     "status": str,                      # Status flags, e.g. "OK", "MAX_STEPS|BOUND_ACTIVE"
     "rms_distance": float}              # root mean square eq. 10 distance of the points

Bad input (missing or damaged file, unsupported format, bad option) prints one line
`sqjax: error: ...` on stderr and exits with status 2; set SQJAX_DEBUG=1 to see tracebacks.

One module per command (`sqjax.cli.segment`, `.demo`, `.render`, `.evaluate`, `.fit`), each with
`add_args(subparsers, parents)` and `run(args) -> int`; `sqjax.cli.common` holds what they share. Only
a command's `run` imports NumPy, JAX and the library, so `sqjax --help` imports neither.
"""

from __future__ import annotations

import atexit
import os
import sys

from . import demo, evaluate, fit, render, segment
from .common import EXIT_FAILURE, EXIT_USAGE, Parser, for_command_line, one_line

COMMANDS = (segment, demo, render, evaluate, fit)
"""The commands' modules, in the order of `sqjax --help`."""


def build_parser() -> Parser:
    """The parser of every command; a parsed command's `func` is its module's `run`."""
    from .. import __version__

    p = Parser(
        prog="sqjax",
        description="Direct part-level segmentation of range images with superquadrics "
        "(recover-and-select; Leonardis, Jaklic, Solina).",
        epilog="Start with 'sqjax demo'. Each command has --help.",
    )
    p.add_argument("--version", action="version", version=f"sqjax {__version__}")
    sub = p.add_subparsers(dest="command", metavar="COMMAND", required=True)
    common = Parser(add_help=False)  # a parent of the sub-parsers, so of their class
    common.add_argument(
        "--no-cache",
        action="store_true",
        help="do not use the on-disk compilation cache (also: SQJAX_NO_CACHE=1); "
        "default folder $XDG_CACHE_HOME/sqjax/jax or ~/.cache/sqjax/jax ($SQJAX_CACHE_DIR)",
    )
    for command in COMMANDS:
        command.add_args(sub, parents=[common])
    return p


def console() -> None:
    """The `sqjax` program (and `python -m sqjax`): `main()`, then exit without the interpreter's
    teardown. The exit handlers run and the output is flushed; what is skipped is freeing every module
    and object one by one, which after a segmentation (JAX, XLA, trimesh, matplotlib loaded) took
    0.6 s of a 5 s warm `sqjax demo` (2026-12-03). Library callers of `main` exit as usual."""
    code = main()
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):  # a closed pipe: nothing more to say
            pass
    atexit._run_exitfuncs()
    os._exit(code)


def main(argv=None) -> int:
    """Run the command line with `argv` (default `sys.argv[1:]`); returns the exit status."""
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as e:  # --help, --version and usage errors (already reported)
        return e.code if isinstance(e.code, int) else EXIT_USAGE
    try:
        from .segment import wants_many

        if args.command == "segment" and wants_many(args):
            # every core a JAX device, batches split over them (`sqjax.parallel`): 30% off a 160 x 120
            # scene (2026-12-03); the split kernels load from the disk cache as the others do (three
            # 640 x 480 mOSD scenes, second call: 26.9 -> 21.4 s wall, 2026-12-08). One input stays on
            # one device. Its second call on two (2026-12-08, segment's seconds, loads included): images
            # (mOSD test40 at 640 x 480, the PCL mug and milk frames) within 0.5 s either way; small
            # clouds (iCub toy, an EMS example) 0-0.6 s slower; Bobkov room2 (124k points), alternating
            # with one device, 12.4 / 13.5 / 14.0 s against 13.6 / 15.3 / 16.0 s, but in
            # benchmarks/files.py (a fresh cache) room1, room2 and its coarse labels ran 18.5, 14.1 and
            # 14.2 s against 18.7, 15.1 and 14.1 s, for 0.1-2.1 s more compile: one input is not split
            from ..parallel import use_cpu_cores

            use_cpu_cores()
        if not getattr(args, "no_cache", False):
            from ..cache import cache_disabled_by_env, enable_compilation_cache

            if not cache_disabled_by_env():
                enable_compilation_cache()
        return args.func(args)
    except BrokenPipeError:  # `sqjax ... | head`: stop quietly (Python docs, "Note on SIGPIPE")
        try:
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        except (OSError, ValueError, AttributeError):
            pass
        return EXIT_FAILURE
    except (ValueError, FileNotFoundError, OSError) as e:
        if os.environ.get("SQJAX_DEBUG"):
            raise
        print(f"sqjax: error: {for_command_line(one_line(e))}", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:
        print("sqjax: interrupted", file=sys.stderr)
        return 130
    except Exception as e:  # a bug: still one line, the traceback on request
        if os.environ.get("SQJAX_DEBUG"):
            raise
        print(
            f"sqjax: internal error: {type(e).__name__}: {one_line(e)} (set SQJAX_DEBUG=1 for the traceback)",
            file=sys.stderr,
        )
        return EXIT_FAILURE
