"""The settings of `segment`, in the parts of the method they belong to, each checked when it is made.

`SegmentOptions` is composed of small frozen dataclasses: the sensor model (`SensorOptions`), the seeds
(`SeedOptions`), the growth of hypotheses (`GrowthOptions`), model selection (`SelectionOptions`), the
fitter's own options (`fitting.FitOptions`, as the refits use them) and what sqjax adds to the paper
(`ExtraOptions`). A bad value raises a `ValueError` that names the class and the field. Every field
also has a flat name (its own; `fit_steps` for `fit.max_steps`), so that `segment(image, window=6)`,
`SegmentOptions.create(window=6)` and the command line's `-o window=6` reach it. Units are those of
the data.
"""

from __future__ import annotations

import dataclasses
from typing import Any, NoReturn

import numpy as np

from .chart import NUM_PARAMS
from .fitting import FitOptions
from .selection import SELECTORS, SelectionWeights


def _checker(obj):
    """Range checks of `obj`'s fields whose errors name the class and the field."""
    cls = type(obj).__name__

    def bad(name, want) -> NoReturn:
        raise ValueError(f"{cls}.{name} must be {want}, got {getattr(obj, name)!r}")

    def number(name, lo=None, hi=None, *, integer=False, optional=False, lo_open=False):
        v = getattr(obj, name)
        if v is None and optional:
            return
        want = ("an integer" if integer else "a finite number") + (" or None" if optional else "")
        if isinstance(v, bool) or not isinstance(v, (int, np.integer) if integer else (int, float, np.number)):
            bad(name, want)
        if not np.isfinite(v):
            bad(name, want)
        if lo is not None and (v <= lo if lo_open else v < lo):
            bad(name, f"{'>' if lo_open else '>='} {lo}")
        if hi is not None and v > hi:
            bad(name, f"<= {hi}")

    def flag(*names):
        for name in names:
            if not isinstance(getattr(obj, name), (bool, np.bool_)):
                bad(name, "True or False")

    return bad, number, flag


@dataclasses.dataclass(frozen=True)
class SensorOptions:
    """The sensor model: what every admission and selection distance is measured in.

    - `noise`: sensor noise std; None = estimated from the data: range images from second
      differences of the depth (`domain.estimate_noise`), clouds as the surface residual at the scale
      of a part (`domain.cloud_noise`: stereo and registered scans are correlated along the surface).
    - `threshold`: admission distance tau (eq. 10); None = `threshold_factor * noise`.
    - `adaptive_noise`: when the noise is estimated, raise it to the typical residual of the seed fits
      (real surfaces are not exact superquadrics).
    - `noise_exponent`: range images: the depth noise is sigma(z) = noise (z / z_median)^k and every
      distance is compared in units of the local sigma (2 for structured light, Khoshelham & Elberink
      2012); None = k estimated from the image, from how its depth's second differences grow with the
      depth (`domain.depth_noise_exponent`: median 2.0 on the mOSD frames, 0.36 on
      constant-noise synthetic scenes); 0 (default) = one noise for the whole image. Measured over the benchmark
      (benchmarks/RESULTS.md): k = 2 lowers the mOSD score (91.9% -> 89.1%; a z^2 sensor term under
      a depth-independent floor for the surfaces' departure from superquadrics: 86.7%; 2026-12-06 late
      night): near objects lose tolerance and split, so the default stays one noise per image.
    - `jump_factor`: two adjacent pixels are apart (a depth discontinuity cuts the adjacency) when
      their 3-D step exceeds `jump_factor` times the typical step plus 6 noise.

    The defaults measured over every suite (benchmarks/RESULTS.md, 2026-12-04, each against the
    defaults of that run: synthetic 99.5%, mOSD 86.0% correct with table 95% and noise regions 8.8%,
    multi-part 95.6%, meshes 57.1%, clouds 74.5%; its spread, `--perturb 1e-5`: mOSD 87.4%, meshes
    53.2%, clouds 77.6%): `threshold_factor` 4 loses multi-part objects (87.5%, volume IoU 0.79),
    meshes (48.1%) and clouds (70.8%) for the table (97%); 2.5 loses mOSD (84.2%, complex 64.1%) for
    clouds (79.5%). `jump_factor` 3 splits the table (93%), 5 joins objects (mOSD 85.3%, complex
    73.4%, synthetic 99.0%). `adaptive_noise`
    False changed one view of one mesh (the seeds' residuals seldom exceed the estimated noise on
    these data); kept for surfaces rougher than their sensor.
    """

    noise: float | None = None
    threshold: float | None = None
    threshold_factor: float = 3.0
    adaptive_noise: bool = True
    noise_exponent: float | None = 0.0
    jump_factor: float = 4.0

    def __post_init__(self):
        _, number, flag = _checker(self)
        for name in ("noise", "threshold"):
            number(name, 0, optional=True, lo_open=True)
        number("threshold_factor", 0, lo_open=True)
        number("noise_exponent", 0, 4, optional=True)
        number("jump_factor", 0, lo_open=True)
        flag("adaptive_noise")


@dataclasses.dataclass(frozen=True)
class SeedOptions:
    """Seeds (the paper's section 3, step 1).

    - `window`, `stride`: seed windows in pixels (None = from the image size); clouds: `window` points
      (None = 48; it also sets the scale of a cloud's noise, `domain.cloud_noise`). Measured on the
      benchmark's clouds suite (benchmarks/RESULTS.md, 2026-12-03): 32 points 75.2% correct, 48
      78.9%, 96 59.6% (multi-part objects merge; single objects then give 1-4 parts).
    - `min_seed_points`: fewest valid points in a seed window (2x the 11 parameters).
    - `seed_inlier_fraction`: a seed is kept when this share of its window lies within tau of its fit
      (statistically consistent with the noise); 0.9, the share growth keeps (`keep_fraction`).
      Measured over every suite (2026-12-04): 0.8 moved mOSD 86.0% -> 86.7% and clouds 74.5% ->
      75.2%, every other suite unchanged (within the spread).
    - `subdivide`: seeds at several scales (range images): a seed window that fails (a depth
      discontinuity inside) is split into its four quadrants, recursively, down to the smallest window
      that can hold `min_seed_points` (5 x 5 for 22), so that parts smaller than a window and the
      surfaces between the depth edges of clutter get seeds. Measured over every suite
      (benchmarks/RESULTS.md, 2026-12-01): mOSD 58.6% -> 68.4% correct (objects 52.7% -> 63.3%,
      table 81% -> 88%), multi-part objects 83.8% -> 92.6%, meshes 24.7% -> 20.8% at T = 0.8 but
      32.5% -> 44.2% at T = 0.5, synthetic 100% both; noise regions rise (mOSD 22.7% -> 33.2%).
      Quadrants only in the reseed rounds (where the first pass left data unexplained) gained less and
      added as much noise. False = one window size, as in the paper.
    - `surface`: range images: in the reseed rounds, the unexplained points that no seed window covers
      get seeds of `min_seed_points` grown along the surface (`seeds.surface_seeds`), so that parts
      narrower than the smallest window (legs two or three pixels wide, faces between the depth edges
      of clutter) get seeds. Measured over every suite (benchmarks/RESULTS.md, 2026-12-03): mOSD
      88.8% -> 88.1% correct (complex 68.8% -> 78.1%; cylindric 92.1% -> 81.0%, as the inside of a
      cup, which a solid would hide, now gets parts of its own; missed 3.9% -> 0.7%, noise regions
      9.6% -> 6.9%), meshes 49.4% -> 55.8% (T = 0.5: 75.3% -> 87.0%), multi-part and synthetic
      unchanged; 14% more time per mOSD scene. In the first round
      as well (with the window seeds) they gained more on meshes (59.7%) but split more objects
      (mOSD 87.0%, table 95%) and took 26% more time.
    """

    window: int | None = None
    stride: int | None = None
    min_seed_points: int = 2 * NUM_PARAMS
    seed_inlier_fraction: float = 0.9
    subdivide: bool = True
    surface: bool = True

    def __post_init__(self):
        bad, number, flag = _checker(self)
        number("min_seed_points", NUM_PARAMS + 1, integer=True)
        number("window", 1, integer=True, optional=True)
        if self.window is not None and self.window * self.window < self.min_seed_points:
            bad(
                "window",
                f"at least {int(np.ceil(np.sqrt(self.min_seed_points)))} (a seed window of "
                f"window^2 pixels must hold min_seed_points = {self.min_seed_points})",
            )
        number("stride", 1, integer=True, optional=True)
        number("seed_inlier_fraction", 0, 1, lo_open=True)
        flag("subdivide", "surface")


@dataclasses.dataclass(frozen=True)
class GrowthOptions:
    """The growth of every hypothesis (the paper's section 3, step 2).

    - `enlarge`: growth factor on a1..a3; `rings`: image-adjacent rings searched per growth step
      (None = 4 per 160 pixels of working-image width and height, the sqrt of the area ratio, so that
      growth per step scales with the image; clouds 4).
    - `admit_factor`: candidates within `admit_factor * tau` of the current model are tried; after the
      refit only points within tau stay, and the step is kept if at least `keep_fraction` of them do.
      (Lets a model turn a box edge, where the next face starts off the current surface.)
    - `max_steps`: cap on growth steps per round.

    Measured over every suite (benchmarks/RESULTS.md, 2026-12-04; defaults: mOSD 86.0%, table 95%,
    multi-part 95.6% (IoU 0.86), meshes 57.1% (89.6% at T = 0.5), clouds 74.5%): `enlarge` 1.3 mOSD
    86.3% (complex 73.4%), meshes 57.1% but 83.1% at T = 0.5, multi-part 94.9% (IoU 0.84);
    `admit_factor` 2 mOSD 87.0% (table 98%), meshes 61.0%, multi-part 94.1% (IoU 0.85), 4 mOSD 84.9%,
    meshes 50.6%; `keep_fraction` 0.95 mOSD 85.6% (cylindric 76.2%), multi-part 97.1% (IoU 0.88),
    clouds 76.4%, 0.85 mOSD 87.7%, multi-part 93.4% (IoU 0.84). None is better beyond the benchmark's
    spread on every suite, and each is worse on at least one: the defaults stay.
    - `max_points`: a region is subsampled (evenly, in index order) to at most this many points for
      its refit; 256 over-determine the 11 parameters more than 20 times. Measured over every suite
      (benchmarks/RESULTS.md, 2026-12-03, against 512): mOSD 86.7% -> 88.8% correct, multi-part
      94.9% -> 95.6%, meshes 48.1% -> 49.4%, synthetic 100% -> 99.5% (one scene), the fit kernel's
      time per mOSD scene 1.6 -> 1.1 s.
    """

    enlarge: float = 1.15
    admit_factor: float = 3.0
    rings: int | None = None
    keep_fraction: float = 0.9
    max_steps: int = 60
    max_points: int = 256

    def __post_init__(self):
        _, number, _ = _checker(self)
        number("enlarge", 1)
        number("admit_factor", 1)
        number("rings", 1, integer=True, optional=True)
        number("keep_fraction", 0, 1, lo_open=True)
        number("max_steps", 0, integer=True)
        number("max_points", 2 * NUM_PARAMS, integer=True)


@dataclasses.dataclass(frozen=True)
class SelectionOptions:
    """Model selection (the paper's section 3, step 3): maximise m^T Q m.

    - `weights`: K1, K2, K3 (None = `SelectionWeights.for_threshold(tau)`: K1 = 1 per explained point,
      K2 = K1 / (2 tau^2), so that a point at tau earns half a point, K3 = 1 per parameter, so that a
      model pays for itself from 11 points on). K3 measured over every suite (2026-12-05, benchmarks/
      RESULTS.md) against 1: 0.5 gave mOSD 90.9% -> 91.2%, multi-part 96.3% -> 93.4%, meshes 66.2% ->
      67.5%, cloud views 75.2% -> 73.3%; 2 gave mOSD 91.6% (complex 82.8% -> 87.5%, noise regions 5.5%
      -> 6.6%), multi-part 96.3%, meshes 62.3%, cloud views 74.5%: the suites move within their
      spread and in opposite directions, so 1 stays. `selector`: "greedy" (the paper), "local" or
      "exact".
    - `select_every`: growth steps between selections (the paper's interleaving). Measured over every
      suite (2026-12-04): 1 lost mOSD (86.0% -> 84.9%, complex 75.0% -> 70.3%), multi-part (95.6% ->
      90.4%) and meshes (57.1% -> 54.5%): a hypothesis needs a few steps to show what it explains
      before it competes.
    - `free_space`: visibility in selection (range images): a model that fills space in front of an
      observed point (the camera saw through it) pays `free_space` * K1 per such point (1 = as much as
      an explained point earns); 0 (default) = the paper's selection. Measured over the benchmark
      (benchmarks/RESULTS.md) with the distance fit, 1 lost mOSD objects (74.4% -> 61.4% correct,
      noise regions 20.4% -> 28.9%; complex 50.0% -> 37.5%) for a gain on multi-part objects
      (85.3% -> 91.2%), and took 55% longer. Visibility decides merges instead (`ExtraOptions.merge`).
    """

    weights: SelectionWeights | None = None
    selector: str = "greedy"
    select_every: int = 3
    free_space: float = 0.0

    def __post_init__(self):
        bad, number, _ = _checker(self)
        if self.selector not in SELECTORS:
            bad("selector", f"one of {SELECTORS}")
        if self.weights is not None and not isinstance(self.weights, SelectionWeights):
            bad("weights", "a SelectionWeights or None")
        number("select_every", 1, integer=True)
        number("free_space", 0)


@dataclasses.dataclass(frozen=True)
class ExtraOptions:
    """What sqjax adds to the paper; each switch off gives the paper's behaviour.

    - `merge`: try joining selected models whose union one superquadric explains (occlusion splits):
      `keep_fraction` of each of the two regions within tau, and (range images) the union's model
      fills no more space the camera saw through (points behind it, pixels with no return) than the
      two parts do, beyond 1 - `keep_fraction` of its points; a union is judged at its size-bounded
      volume when its unbounded fit fails that (`postprocess._union_hypotheses`). A union the camera
      sees mostly from outside is judged hollow: what it saw through the opening (a cup's or a bowl's
      inside, on the model's far surface) is explained and not counted against it (`postprocess._hollow`;
      2026-12-05: mOSD 87.4% -> 89.8%, cylindric 81.0% -> 88.9%, meshes 62.3% -> 66.2%, multi-part
      97.1% -> 96.3%). Measured over every suite (2026-12-04): False lost mOSD (86.0% -> 81.1%;
      occluded 87.5% -> 70.8%, table 95% -> 93%), meshes (57.1% -> 55.8%) and synthetic scenes
      (99.5% -> 99.0%), gained clouds (74.5% -> 77.6%, within their spread). A union the selection
      keeps grows on and merging repeats (`segmentation.MERGE_ROUNDS`): one round left a sphere
      sampled all round in 3-11 caps; measured 2026-12-05 (evening): mOSD 89.8% -> 90.9%, closed
      clouds (dense) 18 -> 19 of 24 parts, the rest within their spreads. The pairs tried are each
      model's nearest few (`postprocess.merge_candidates`: by bounding spheres, and in range images
      by the gap between the regions' points, so that an occluder's pieces meet; 2026-12-06: mOSD
      91.2% -> 91.9%); in a cloud, which has no camera to tell an occluded gap from empty space,
      only pairs whose regions touch (2026-12-07: clouds 79.8% -> 84.2% over their spread, Bobkov's
      rooms 27 -> 28 of 92 parts, room2 thinned 10 -> 21 of 93).
    - `reseed`: rounds of a second chance after the final selection: seed again where no selected model
      explains the data, grow those seeds and select among old and new (parts whose hypotheses lost
      early to a neighbour's). 0 = the paper's single pass. Measured over every suite (2026-12-04):
      one round instead of two moved every suite within its spread (mOSD 86.0% -> 85.6%, meshes
      57.1% -> 58.4%, clouds 74.5% -> 73.9%): the benchmark does not separate one round from two.
    - `min_exclusive`: after the final selection, a model explaining less than this share of its
      region alone (the rest is also explained by others) is dropped as redundant; so is one that
      explains alone fewer than `SeedOptions.min_seed_points` points, too few to determine its
      parameters (measured over every suite, 2026-12-03: noise regions mOSD 6.9 -> 6.4%, multi-part
      2.9 -> 2.2%, meshes 31.6 -> 22.3%, meshes correct 55.8 -> 57.1%, nothing else changed).
    - `propagate`: the label image also covers the valid pixels that no final model explains within
      tau but that the surface joins to labelled ones (adjacency cut at depth discontinuities): ring
      by ring from the labelled pixels, each takes the neighbouring label whose model is nearest. The
      models describe a part's volume; the label image partitions the surface, including what a
      superquadric does not follow (the rounded rim of a box, the curved side of a bowl, mixed pixels
      at edges). Measured over every suite (benchmarks/RESULTS.md, 2026-12-02): mOSD 76.5% -> 82.1%
      correct (objects 70.4% -> 77.4%, noise regions 21.5% -> 15.3%, table 100% both), meshes 40.3%
      -> 42.9%, multi-part objects (85.3%) and synthetic scenes (97.7%) unchanged. A frame segmented
      at a working step is labelled at its own size the same way (`labelling.label_full`: along the
      full-size surface, under the labelled working pixels). False = label only the pixels a model
      explains (the paper).
    - `part_volumes`: each final model is refitted to its part's points with the fitter's size bound,
      from several starts, and the part keeps the candidate that best agrees with the observations
      (the part's points it explains, less the observed points and empty pixels whose viewing rays
      it blocks; among equals the smallest volume), unless the growth model agrees better by more
      than 1 - keep_fraction of the part's points (`postprocess.part_volumes`). Growth extrapolates,
      so without it a part is often a sheet metres wide or a leg whose far end lies outside the view.
      Labels are unchanged. Measured over every suite (benchmarks/RESULTS.md, 2026-12-02): median
      volume IoU of matched multi-part parts 0.47 -> 0.86 (tables 0.11 -> 0.59, chairs 0.33 -> 0.62,
      arms 0.40 -> 0.97); Hoover scores of every suite unchanged. False = the growth models.
    - `visibility`: range images: a point is explained by a model only if the camera did not see
      through the model to reach it: its viewing ray must not pass through the model's solid deeper
      than tau (`visibility.seen_through`). Without it a model may explain a surface with its back
      face (a slab in front of a wall, a box that explains the table beside it with its underside,
      a model bulging towards the camera) and take pixels its visible side would hide. Rays that
      only graze a model (its rim, within the noise) do not count. Measured over every suite
      (benchmarks/RESULTS.md, 2026-12-03): mOSD 76.8% -> 86.7% correct (objects 71.2% -> 84.5%,
      noise regions 15.3% -> 7.8%; complex 51.6% -> 67.2%, occluded 54.2% -> 87.5%, boxes 87.7% ->
      100%, cylindric 95.2% -> 90.5%: a bowl's inside, seen through its opening, is no longer
      explained by one convex model; table 98% -> 95%), multi-part objects 86.8% -> 94.9%, meshes
      41.6% -> 48.1%, synthetic 99.0% -> 100%. The first test, that the surface faces away (n . v
      > 0.2 for the outward normal and the viewing ray), was tried alone: mOSD 80.7%, cylindric
      85.7% (rims of slightly large models). False = the paper's eq. 10 distance alone.
    - `subsample`: range images are segmented at every `subsample`-th row and column, then every pixel
      of the input is labelled by the final models (the paper subsampled its dense images). None =
      `segmentation.working_step`: the step that brings the image nearest to
      `segmentation.WORKING_PIXELS` (160 x 120, the resolution every default here was measured at:
      640 x 480 -> 4), or a finer one while the working image keeps at most
      `segmentation.WORKING_VALID` valid pixels (an object that fills an eighth of a 320 x 240 render:
      step 1); 1 = the slow exact path.
      Point clouds likewise: segmented on one in `subsample` of their points (a fixed random choice,
      `segmentation.working_subset`), every input point then labelled; None = nearest to
      `segmentation.WORKING_POINTS` (76,800: four working images' worth, measured on Bobkov's rooms).
    """

    merge: bool = True
    reseed: int = 2
    min_exclusive: float = 0.2
    propagate: bool = True
    part_volumes: bool = True
    visibility: bool = True
    subsample: int | None = None

    def __post_init__(self):
        _, number, flag = _checker(self)
        number("reseed", 0, integer=True)
        number("min_exclusive", 0, 1)
        number("subsample", 1, integer=True, optional=True)
        flag("merge", "propagate", "part_volumes", "visibility")


SEGMENTATION_FIT = FitOptions(max_steps=10)
"""The fitter's options in segmentation: 10 LM steps per refit (a growth step moves a model little);
each call sets `multistart` (seeds, merges) and `size_bound` (the part-volume refits) itself.
Measured over every suite against 6 steps (benchmarks/RESULTS.md, 2026-12-04; two runs each, as is
and with `--perturb 1e-5`): 6 steps gave mOSD 88.4% both times (10: 86.0 / 87.4%), meshes 59.7 /
57.1% (57.1 / 53.2%), multi-part 94.9% (95.6%), in 0.89 of the time, but the paper's Figure 3 block,
seen in two pieces behind the cylinder, stayed two parts (the paper-scene test) and two more
single-object clouds split (the iCub box and car, 2 parts each)."""

_GROUPS = {
    "sensor": SensorOptions,
    "seeds": SeedOptions,
    "growth": GrowthOptions,
    "selection": SelectionOptions,
    "extras": ExtraOptions,
}
_ALIASES = {"fit_steps": ("fit", "max_steps")}


def _flat_names() -> dict[str, tuple[str, str]]:
    """{flat name: (group, field)} of every option."""
    out = {f.name: (g, f.name) for g, cls in _GROUPS.items() for f in dataclasses.fields(cls)}
    return {**out, **_ALIASES}


@dataclasses.dataclass(frozen=True)
class SegmentOptions:
    """Settings of `segment`: one part per step of the method (see each part's docstring).

    Build it from parts (`SegmentOptions(seeds=SeedOptions(window=6))`) or from flat names
    (`SegmentOptions.create(window=6, reseed=0)`; `fit_steps` is `fit.max_steps`). `fit` is the
    fitter's `FitOptions` as the refits use it (undeformed models: `deform` must be False).
    """

    sensor: SensorOptions = dataclasses.field(default_factory=SensorOptions)
    seeds: SeedOptions = dataclasses.field(default_factory=SeedOptions)
    growth: GrowthOptions = dataclasses.field(default_factory=GrowthOptions)
    selection: SelectionOptions = dataclasses.field(default_factory=SelectionOptions)
    fit: FitOptions = SEGMENTATION_FIT
    extras: ExtraOptions = dataclasses.field(default_factory=ExtraOptions)

    def __post_init__(self):
        bad, _, _ = _checker(self)
        for name, cls in {**_GROUPS, "fit": FitOptions}.items():
            if not isinstance(getattr(self, name), cls):
                bad(name, f"a {cls.__name__}")
        if self.fit.deform:
            bad("fit", "undeformed (deform=False): segmentation's distance kernels are of undeformed models")
        if self.growth.max_points < self.seeds.min_seed_points:
            raise ValueError(
                f"GrowthOptions.max_points must be >= SeedOptions.min_seed_points = {self.seeds.min_seed_points}, "
                f"got {self.growth.max_points}"
            )

    @classmethod
    def names(cls) -> dict[str, tuple[str, str]]:
        """{flat name: (part, field)} of every option."""
        return _flat_names()

    @classmethod
    def create(cls, **flat: Any) -> SegmentOptions:
        """Options from flat names (`window=6`, `fit_steps=8`); a `TypeError` names an unknown one."""
        return cls().replace(**flat)

    def replace(self, **flat: Any) -> SegmentOptions:
        """A copy with the options of the given flat names changed."""
        names = _flat_names()
        unknown = sorted(set(flat) - set(names))
        if unknown:
            raise TypeError(f"SegmentOptions: unknown option(s) {', '.join(unknown)}; known: {', '.join(names)}")
        groups: dict[str, dict] = {}
        for key, value in flat.items():
            group, field = names[key]
            groups.setdefault(group, {})[field] = value
        parts = {}
        for group, kw in groups.items():
            try:
                parts[group] = dataclasses.replace(getattr(self, group), **kw)
            except ValueError as e:  # name the option as it was given (fit_steps is FitOptions.max_steps)
                given = [k for k, (g, _) in names.items() if g == group and k in flat]
                raise ValueError(f"{e} (option {', '.join(given)})") from None
        return dataclasses.replace(self, **parts)

    @classmethod
    def parse(cls, key: str, text: str) -> tuple[str, Any]:
        """A command-line `KEY=VALUE` -> (flat name, value of the field's type). KEY is a flat name or
        `part.field` (`-` for `_`); VALUE `none` / `auto` for an optional field, `true` / `false`. A
        `ValueError` names the key. `weights` takes no text form."""
        names = _flat_names()
        key = key.strip().replace("-", "_")
        if "." in key:
            key = next((n for n, path in names.items() if ".".join(path) == key), key)
        if key not in names or key == "weights":
            known = ", ".join(n for n in names if n != "weights")
            raise ValueError(f"unknown segment option {key!r} (known: {known})")
        group, field = names[key]
        spec = next(f for f in dataclasses.fields(FitOptions if group == "fit" else _GROUPS[group]) if f.name == field)
        default, annotation, text = spec.default, str(spec.type), text.strip()
        want = (
            "true or false"
            if isinstance(default, bool)
            else "an integer"
            if isinstance(default, int) or "int" in annotation
            else "a number"
            if isinstance(default, float) or "float" in annotation
            else "text"
        ) + (" or none" if default is None or "None" in annotation else "")
        try:
            if text.lower() in ("none", "auto", "") and (default is None or "None" in annotation):
                return key, None
            if isinstance(default, bool):
                if text.lower() not in ("true", "false", "1", "0", "yes", "no"):
                    raise ValueError(text)
                return key, text.lower() in ("true", "1", "yes")
            if isinstance(default, int) or "int" in annotation:
                return key, int(text)
            if isinstance(default, float) or "float" in annotation:
                return key, float(text)
            return key, text
        except ValueError:
            raise ValueError(f"bad value for segment option {key}: {text!r} (expected {want})") from None

    def flat(self) -> dict[str, Any]:
        """{flat name: value} of every option."""
        return {key: getattr(getattr(self, g), f) for key, (g, f) in _flat_names().items()}
