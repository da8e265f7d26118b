"""Property-based fuzzing of the registration API (hypothesis): random shapes, dtypes, repeated points,
degenerate and far-from-origin clouds, NaN rows and initial guesses. Only the named exceptions of
`genreg_core.errors` may escape, and every result is finite. The "ci" profile (test/conftest.py) runs a few
hundred examples per property; HYPOTHESIS_PROFILE=local runs 10,000."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from genreg_core.config import SCENE_REGISTRATION, RefineConfig, RegistrationConfig
from genreg_core.errors import GenRegError
from genreg_core.registration import Registrar

SHAPES = ("blob", "repeated", "one_point", "line", "plane", "grid", "sphere")
DTYPES = (np.float32, np.float64) * 8 + (np.int32, np.uint8, np.float16, np.int64)


def cloud(kind: str, n: int, rng: np.random.Generator) -> np.ndarray:
    """n points of a shape, float64, about unit size."""
    if kind == "blob":
        return rng.standard_normal((n, 3))
    if kind == "repeated":  # a few distinct points, each many times
        return rng.standard_normal((max(1, n // 50), 3))[rng.integers(0, max(1, n // 50), n)]
    if kind == "one_point":
        return np.repeat(rng.standard_normal((1, 3)), n, axis=0)
    if kind == "line":
        return rng.random((n, 1)) * rng.standard_normal(3)
    if kind == "plane":
        return rng.random((n, 2)) @ rng.standard_normal((2, 3))
    if kind == "grid":  # integer lattice: many equal coordinates, exact ties in every distance
        return rng.integers(0, 4, (n, 3)).astype(np.float64)
    u = rng.standard_normal((n, 3))
    return u / np.linalg.norm(u, axis=1, keepdims=True)


SCALES = st.integers(-30, 30)  # powers of ten
OFFSETS = st.sampled_from([0.0, 1e3, 1e6, -1e9, 1e15])


@st.composite
def clouds(draw: st.DrawFn, scale: int | None = None, offset: float | None = None) -> np.ndarray:
    """An (n, c) array: a shape, scaled by 10^`scale` (-30 to 30) and moved by `offset` (up to 1e15; drawn
    when not given), in a dtype, with some duplicated, NaN or Inf rows and, rarely, the wrong number of
    columns."""
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    n = draw(st.one_of(st.integers(0, 1500), st.integers(300, 1500), st.integers(300, 1500)))
    points = cloud(draw(st.sampled_from(SHAPES)), n, rng)
    scale = draw(SCALES) if scale is None else scale
    points = points * 10.0**scale + (draw(OFFSETS) if offset is None else offset)
    if n and draw(st.booleans()):  # dual returns
        points = np.concatenate([points, points[rng.integers(0, n, n // 10 + 1)]])
    if n and draw(st.booleans()):  # NaN or Inf rows
        points[rng.integers(0, len(points), len(points) // 10 + 1)] = draw(st.sampled_from([np.nan, np.inf, -np.inf]))
    with np.errstate(over="ignore", invalid="ignore"):
        points = points.astype(draw(st.sampled_from(DTYPES)))
    columns = draw(st.sampled_from([3] * 30 + [2, 4]))
    return points[:, :columns] if columns < 3 else np.pad(points, ((0, 0), (0, columns - 3)))


@st.composite
def guesses(draw: st.DrawFn) -> np.ndarray | None:
    """None, a rigid transform anywhere, or a broken matrix."""
    kind = draw(st.sampled_from(["none", "none", "rigid", "scaled", "nan"]))
    if kind == "none":
        return None
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    T = np.eye(4)
    T[:3, :3] = Rotation.random(random_state=rng).as_matrix()
    T[:3, 3] = rng.standard_normal(3) * 10.0 ** draw(st.integers(-3, 12))
    if kind == "scaled":
        T[:3, :3] *= 2.0
    if kind == "nan":
        T[0, 0] = np.nan
    return T


@pytest.fixture(scope="module")
def registrars() -> list[Registrar]:
    """The default object model with point-to-plane refinement (its extra passes included), and the scene
    profile (`config.SCENE_REGISTRATION`: GICP with its tight stage, one pass)."""
    return [Registrar.from_checkpoint(config=RegistrationConfig(refine=RefineConfig(method="point_to_plane"))),
            Registrar.from_checkpoint("7scenes", SCENE_REGISTRATION)]


def check(result) -> None:
    """Every number of a result is finite and the transform is rigid."""
    T = result.transformation
    assert T.shape == (4, 4) and np.isfinite(T).all()
    assert np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-6) and np.allclose(T[3], [0, 0, 0, 1])
    for value in (result.fitness, result.tight_fitness, result.inlier_ratio, result.inlier_rmse, result.confidence):
        assert np.isfinite(value)
    assert 0.0 <= result.confidence <= 1.0
    assert np.isfinite(result.aligned_source).all() and np.isfinite(result.source_generated).all()
    assert result.covariance is None or np.isfinite(result.covariance).all()


@st.composite
def pairs(draw: st.DrawFn) -> tuple[np.ndarray, np.ndarray]:
    """Two clouds, mostly at one scale and place (as a sensor's), sometimes each anywhere."""
    scale, offset = draw(SCALES), draw(OFFSETS)
    apart = draw(st.integers(0, 4)) == 0
    source = draw(clouds(scale, offset))
    target = draw(clouds() if apart else clouds(scale + draw(st.integers(-1, 1)), offset))
    return source, target


@settings(suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
@given(pair=pairs(), guess=guesses(), which=st.integers(0, 1))
def test_only_named_errors_and_finite_results(registrars, pair, guess, which):
    source, target = pair
    try:
        result = registrars[which].register(source, target, initial_guess=guess)
    except GenRegError as exc:
        event(f"raised {type(exc).__name__}")  # the tallies show in --hypothesis-show-statistics
        return
    event("registered")
    check(result)


@settings(suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
@given(seed=st.integers(0, 2**32 - 1), shape=st.sampled_from(SHAPES), offset=st.sampled_from([0.0, 1e4, 1e6]),
       share=st.floats(0.0, 0.5))
def test_repeated_points_far_from_the_origin_register(registrars, seed, shape, offset, share):
    """float32 clouds with up to half their points repeated, at up to 1e6 m: a result or TooFewPointsError."""
    rng = np.random.default_rng(seed)
    points = cloud(shape, 800, rng) * 5.0
    points = np.concatenate([points, points[rng.integers(0, 800, int(share * 800))]])
    moved = points @ Rotation.random(random_state=rng).as_matrix().T + rng.standard_normal(3)
    try:
        result = registrars[1].register((points + offset).astype(np.float32), (moved + offset).astype(np.float32))
    except GenRegError as exc:
        assert "distinct" in str(exc)  # only a cloud with too few distinct points may be refused
        event("too few distinct points")
        return
    event("registered")
    check(result)
