"""Property-based fuzz (hypothesis) of the superquadric functions: finite values and gradients.

Issue 15 ("non-finite maths"): `distance`'s reverse-mode gradient near the centre, `radial_distance`
beyond |x| = 1.8e19, gradients with respect to tiny sizes. CI-sized here (a few hundred cases per
function); `python benchmarks/fuzz.py` runs the same check on 1e5 cases per function.
"""

import importlib.util
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

_spec = importlib.util.spec_from_file_location(
    "sqjax_fuzz", Path(__file__).resolve().parents[1] / "benchmarks" / "fuzz.py"
)
fuzz = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(fuzz)

_CHECKERS = {name: fuzz.checker(name) for name in fuzz.FUNCTIONS}

mag = st.floats(-20, 18)  # log10 |x|
log_size = st.floats(-6, 6)
unit = st.floats(-1, 1)


@st.composite
def case(draw):
    size = 10.0 ** np.array([draw(log_size) for _ in range(3)])
    if draw(st.booleans()):
        size[:] = size[0]
    eps = np.array([draw(st.floats(0.1, 1.9)), draw(st.floats(0.1, 1.9))])
    d = np.array([draw(unit) for _ in range(3)])
    kind = draw(st.sampled_from(["free", "axis", "near", "zero", "surface"]))
    if kind == "axis":
        d = np.eye(3)[draw(st.integers(0, 2))] * (1 if draw(st.booleans()) else -1)
    n = np.linalg.norm(d)
    d = d / n if n > 0 else np.array([0.0, 0.0, 1.0])
    x = {
        "free": d * 10.0 ** draw(mag),
        "axis": d * 10.0 ** draw(mag),
        "zero": 0.0 * d,
        "near": d * size.max() * 10.0 ** draw(st.floats(-12, -6)),
        "surface": d * size * draw(st.floats(0.9, 1.1)),
    }[kind]
    q = np.array([draw(unit) for _ in range(4)]) + np.array([1e-3, 0, 0, 0])
    R = fuzz._rotations(np.random.default_rng(0), 1)[0] if kind == "axis" else None
    if R is None:
        w, a, b, c = q / np.linalg.norm(q)
        R = np.array(
            [
                [1 - 2 * (b * b + c * c), 2 * (a * b - c * w), 2 * (a * c + b * w)],
                [2 * (a * b + c * w), 1 - 2 * (a * a + c * c), 2 * (b * c - a * w)],
                [2 * (a * c - b * w), 2 * (b * c + a * w), 1 - 2 * (a * a + b * b)],
            ]
        )
    if kind == "axis":
        R = np.eye(3)
    deform = draw(st.booleans())
    if deform and np.linalg.norm(x) > 1e3 * size.max():  # deformations only near the model (fuzz.py)
        x = x * (1e3 * size.max() / np.linalg.norm(x))
    taper = np.array([draw(unit), draw(unit)]) if deform else np.zeros(2)
    bend = (
        np.array([10.0 ** draw(st.floats(-8, 0)) / size.max(), draw(st.floats(-3.1, 3.1))]) if deform else np.zeros(2)
    )
    f32 = lambda v: np.asarray(v, np.float32)[None]
    return {
        "point": f32(x),
        "size": f32(size),
        "epsilon": f32(eps),
        "rotation": f32(R),
        "translation": f32(np.zeros(3)),
        "taper": f32(taper),
        "bend": f32(bend),
    }


@pytest.mark.parametrize("name", fuzz.FUNCTIONS)
@settings(max_examples=60, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.too_slow])
@given(c=case())
def test_values_and_gradients_finite(name, c):
    """Value and reverse-mode gradients (point, size, exponents) finite for every finite input."""
    assert bool(np.asarray(_CHECKERS[name](c))[0]), c


@pytest.mark.parametrize("name", fuzz.FUNCTIONS)
def test_random_batch_finite(name):
    """A seeded batch of 2000 cases of the benchmark's distribution (axes, centre, surface, far away)."""
    c = fuzz.cases(np.random.default_rng(7), 2000)
    ok = np.asarray(_CHECKERS[name](c))
    assert ok.all(), {k: v[~ok][:1].tolist() for k, v in c.items()}
