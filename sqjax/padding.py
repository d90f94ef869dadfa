"""How arrays are padded before they reach a jitted kernel: every policy of the package, in one place.

A jitted kernel compiles once per input shape (5-20 s each on CPU), so every batch entry point pads its
inputs to a few fixed sizes, and the padding rows repeat a real row (or zeros) so that no padded problem
can produce a NaN. Each policy below says which kernel it serves and why its sizes are what they are.
"""

from __future__ import annotations

import jax
import numpy as np

from . import parallel

CHUNK_POINTS = 4096
"""On CPU the fitter fits at most `CHUNK_POINTS // N` problems of N points at a time (`fit_chunk`):
a chunk's points and every intermediate of its LM steps then stay in cache."""

MULTISTART_CANDIDATES = 256
"""On CPU the multistart fits at most this many candidates at a time (problems x starting candidates in
one vmap), fewer problems than `CHUNK_POINTS` allows when the candidates are many. 32 problems of 18
candidates (576) in one vmap on each of two CPU devices (`parallel`) left XLA's runtime waiting
forever, every thread idle (jax 0.10.2, N = 32 to 128 points; 24 problems per device ran, and so did
one device with any number): a union fit of the merge between small parts, or `fit()` of 64 problems
with `use_cpu_cores(2)`. 14 problems of 18 (252): fits/s unchanged within the machine's drift (1
device, 2026-12-04: N = 128 310 vs 330, N = 256 176-189 vs 182 before)."""


def fit_chunk(K: int, N: int, candidates: int, screened: int) -> int:
    """Problems the fit kernels fit side by side on CPU (`solver.map_problems`): K problems of N points,
    `candidates` starts each side by side on `screened` of the points (the multistart; 1 and N for a
    warm start).

    At most `CHUNK_POINTS // points` and, with several starts, `MULTISTART_CANDIDATES // candidates`,
    rounded down to a power of two, so that it divides the padded K: a remainder is a second copy of the
    whole fit in the program (14 problems of a 64-problem call compiled in 12-15 s instead of 7 s; the
    merges' multistart in segmentation likewise). `points` is the screened points on one CPU device, N
    on several. The screening is most of a multistart's work, and on one device XLA spreads a wider
    chunk's operations over the cores: N = 1024 and 4096 (4 and 1 problems at a time when sized by N,
    8 now) ran 1.2-1.3x faster (K = 64, 2026-12-06, RESULTS.md). Split over one device per core (the
    command line, the benchmarks), wider chunks gained nothing (0.90-0.97x, within the drift)."""
    points = screened if parallel.cpu_devices() == 1 else N
    limit = max(1, CHUNK_POINTS // max(points, 1))
    if candidates > 1:
        limit = min(limit, max(1, MULTISTART_CANDIDATES // candidates))
    return 1 << (min(limit, max(K, 1)).bit_length() - 1)


def fit_points(n: int, screen: int | None) -> int:
    """Rows of `fit`'s kernel for problems of at most n points: powers of two from 128, except that with
    a multistart screened on `screen` points (`FitOptions.screen_points`; None: no screening), every n
    from 129 to 4 x `screen` shares one size (1024 by default).

    For those n the screening (18 starts x 16 LM steps on `screen` points, all of them when n is
    smaller) is the kernel's work; the padded rows only lengthen the finish (8 LM steps on every row):
    1024 rows cost about 10% more than 256 (`FitOptions.point_iterations`: 86k against 78k
    point-steps; measured 2026-12-07: +10% for 64 problems of 200 points, +10-15% for one). A user's
    loop over n from 129 to 1024 then compiles (or loads from the cache) one kernel instead of three,
    each 7-10 s to compile and 0.4-0.5 s to load on the 2-core machine."""
    rows = bucket(n, 128)
    if screen is not None and 128 < rows < 4 * screen:
        return bucket(4 * screen, 128)
    return rows


ACCELERATOR_BATCHES = (1, 4, 16, 32, 64)
"""Problems per call of the fit kernel on an accelerator, for callers whose count moves (`fit_call_sizes`)."""

PAIRS = 1 << 15
"""Most (model, point) pairs per call of a pair kernel (eq. 10 distances, free-space tests)."""


def pair_split(n: int) -> bool:
    """Whether a pair kernel's call of n pairs is split over the CPU devices: only the largest (`PAIRS`);
    smaller calls run faster whole (measured 2026-12-05, labels bit-identical either way)."""
    return parallel.splits(n, PAIRS)


POINT_ROWS = 4096
"""A scene's points are padded to a multiple of this on the device (the pair kernels index into them)."""


def bucket(n: int, minimum: int = 32) -> int:
    """The next power of two >= n, at least `minimum`: `fit`'s K and N, small host-side batches."""
    return max(minimum, 1 << max(int(n) - 1, 0).bit_length())


def pad_rows(a: np.ndarray, n: int, fill) -> np.ndarray:
    """a (m, ...) followed by copies of `fill` up to n rows (a itself when m >= n)."""
    return np.concatenate([a, np.repeat(np.asarray(fill)[None], n - a.shape[0], 0)]) if n > a.shape[0] else a


def fit_call_sizes(N: int, quarter: bool = True) -> tuple[int, ...]:
    """The batch sizes of the fit kernel's calls for problems of N (padded) points (`fit_calls`), for
    callers whose number of problems moves from call to call (segmentation's refits), so that each
    (N, options) compiles few kernels.

    On CPU, which fits a call's problems `CHUNK_POINTS // N` at a time anyway, that chunk and (with
    `quarter`) a quarter of it, per CPU device (`parallel`). A padded problem costs as much as a real
    one, and the late growth steps refit one or two models: with one size a third of the problems
    fitted were padding (mOSD at 160 x 120, N = 256); a quarter-size call costs a third of a full one.
    Segmentation asks for the quarter size for warm-started refits (3-4 s to compile, 0.84 of the
    time per scene), not for the multistart's few calls (the merges': 7-9 s to compile, for about
    0.1 s per scene). On an accelerator, which fits them side by side, `ACCELERATOR_BATCHES`."""
    if jax.default_backend() != "cpu":
        return ACCELERATOR_BATCHES
    chunk = max(1, CHUNK_POINTS // N) * parallel.cpu_devices()
    return tuple(sorted({max(chunk // 4, parallel.cpu_devices()) if quarter else chunk, chunk}))


def fit_calls(K: int, N: int, quarter: bool = True):
    """(start, size) of the fit kernel's calls for K problems of N points (`fit_call_sizes`, `calls`)."""
    sizes = fit_call_sizes(N, quarter)
    if jax.default_backend() != "cpu":  # side by side: one padded call beats two
        n = next((b for b in sizes if b >= K), sizes[-1])
        return ((s, n) for s in range(0, K, n))
    return calls(K, sizes)


def refit_points(largest: int, max_points: int) -> int:
    """Points per problem of a segmentation refit whose largest region has `largest` points (regions are
    subsampled to `max_points`): 128 when every region fits (seed windows at 160 x 120 hold about 100),
    else `max_points` rounded up to a power of two: two kernels per option set. No more than the largest
    region needs, rounded likewise: a `max_points` far above the data's size (`-o max_points=100000` on
    a 3,072-pixel image) padded every refit to it, 25x the time, and 1e8 asked for 375 GiB."""
    cap = bucket(min(max_points, max(largest, 1)), 32)
    return min(128, bucket(max_points, 32)) if min(largest, max_points) <= 128 else cap


PAIR_SIZES = (1024, 4096, 16384, PAIRS)
"""The call sizes of the pair kernels (`calls`): four compiled sizes (about 1 s each on CPU). A larger
call costs less per pair (on 2 CPU cores 330 ns a distance at 1024 pairs, 120 ns at 32768), a padded
pair as much as a real one."""


def calls(E: int, sizes: tuple[int, ...] = PAIR_SIZES):
    """(start, size) of the kernel calls covering E rows with calls of the given `sizes` (ascending):
    the smallest size that holds what is left, unless more than half of it would be padding, then a
    full call of the largest size that fits (5,000 pairs: 4096 + 1024, not 16384 with 11,000 padded)."""
    s = 0
    while s < E:
        left = E - s
        n = next((n for n in sizes if n >= left), sizes[-1])
        if n > 2 * left and n > sizes[0]:
            n = max(m for m in sizes if m <= left)
        yield s, n
        s += n


def point_rows(P: int) -> int:
    """Device rows for a scene of P points: the next multiple of `POINT_ROWS`."""
    return -(-P // POINT_ROWS) * POINT_ROWS
