"""More network passes while unsure (`RegistrationConfig.passes`): other subsamples and PDSAC draws, the
result the calibration finds most probably right wins (the truth: a training crop's known transform)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from genreg_core.config import RefineConfig, RegistrationConfig
from genreg_core.data import load_modelnet40
from genreg_core.data.modelnet40 import rpmnet_crop_pair
from genreg_core.metrics import transform_errors
from genreg_core.registration import Registrar


def test_a_flipped_crop_is_saved_by_another_pass_and_a_guess_asks_for_one():
    """A ModelNet40 training crop (shape 2406, crop seed (2030, 2406)) that one pass registers upside down
    (169 deg off, confidence 0.07): with four passes the right pose wins (0.5 deg, confidence 0.94), and it is
    one of the four single passes (seeds 0-3), the one the calibration scores highest. With an initial guess
    only one pass runs."""
    shapes = load_modelnet40("train", "seen")
    source, target, T = rpmnet_crop_pair(shapes.points[2406].astype(np.float64), np.random.default_rng((2030, 2406)))
    cfg = RegistrationConfig(refine=RefineConfig(method="point_to_point"))
    four = Registrar.from_checkpoint("modelnet40_partial", cfg)
    singles = [Registrar.from_checkpoint("modelnet40_partial", replace(cfg, seed=seed, passes=1)) for seed in range(4)]
    one = singles[0].register(source, target)
    assert transform_errors(one.transformation, T)[0] > 90.0 and one.confidence < 0.5
    result = four.register(source, target)
    assert transform_errors(result.transformation, T)[0] < 2.0 and result.confidence > 0.8
    assert result.passes == 4 and one.passes == 1
    passes = [reg.register(source, target) for reg in singles]
    assert any(np.allclose(p.transformation, result.transformation, atol=1e-9) for p in passes)
    assert max(p.confidence for p in passes) >= result.confidence
    guessed = four.register(source, target, np.eye(4))
    assert guessed.passes == 1
