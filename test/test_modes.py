"""PDSAC's other modes: distinct hypotheses, refit on their inliers, verified against the clouds (the truth:
hypotheses and correspondences built from known rotations, and a training pair's ground-truth pose)."""

from __future__ import annotations

import dataclasses

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from genreg_core.config import SCENE_REGISTRATION, PDSACConfig
from genreg_core.data import FramePairs, RGBDSequence
from genreg_core.geometry import rotation_angle
from genreg_core.metrics import transform_errors
from genreg_core.pdsac import PDSACResult, both_directions, distinct_modes
from genreg_core.registration import Registrar


def about_z(degrees: float) -> torch.Tensor:
    T = torch.eye(4, dtype=torch.float64)
    T[:3, :3] = torch.from_numpy(Rotation.from_euler("z", degrees, degrees=True).as_matrix())
    return T


def test_distinct_modes_are_apart_in_score_order_and_refit_on_their_inliers():
    rng = np.random.default_rng(0)
    src = torch.from_numpy(rng.standard_normal((1, 200, 3)))
    true = about_z(33.0)  # half the correspondences agree with 33 deg, half with 0 deg
    dst = torch.cat([src[:, :100] @ true[:3, :3].T, src[:, 100:]], dim=1)
    angles = [0.0, 5.0, 31.0, 60.0, 62.0, 120.0]  # scored in this order (best first)
    hypotheses = torch.stack([about_z(a) for a in angles])[None]
    scores = torch.arange(len(angles), dtype=torch.float64)[None]
    res = PDSACResult(hypotheses[:, 0], hypotheses, scores, torch.softmax(-scores, 1), torch.ones(1, 200, dtype=bool))
    empty = PDSACResult(hypotheses[:, 0], hypotheses[:, :0], scores[:, :0], scores[:, :0], res.inliers)
    both, both_scores = both_directions(res, empty)
    cfg = PDSACConfig(modes=4, mode_separation=15.0, inlier_threshold=0.05)
    modes = distinct_modes(about_z(0.0)[None], both, both_scores, src, dst, cfg)
    found = [float(np.degrees(rotation_angle(M[:3, :3].numpy()))) for M in modes[0]]
    assert np.allclose(found[:2], [33.0, 60.0], atol=1e-6)  # 31 refit to 33 on its inliers; 5 and 62 are near others
    assert abs(found[2] - 120.0) < 1e-6
    assert distinct_modes(about_z(0.0)[None], both, both_scores, src, dst,
                          dataclasses.replace(cfg, modes=1)).shape == (1, 0, 4, 4)


def test_a_pair_whose_pdsac_winner_is_wrong_is_saved_by_a_verified_mode():
    """Redkitchen training frames 90 apart, the source kidnapped: PDSAC's best hypothesis refines to 77 deg
    off; another mode verifies better and is right."""
    item = FramePairs(RGBDSequence.redkitchen(), 90, range(800), kidnap=True, seed=2029)[0]
    source, target = item["source"][::2], item["target"][::2]
    shipped = Registrar.from_checkpoint("7scenes", SCENE_REGISTRATION)
    winner_only = Registrar.from_checkpoint("7scenes", dataclasses.replace(
        SCENE_REGISTRATION, pdsac=dataclasses.replace(SCENE_REGISTRATION.pdsac, modes=1)))
    wrong, right = winner_only.register(source, target), shipped.register(source, target)
    assert transform_errors(wrong.transformation, item["transform"])[0] > 10.0
    rotation_error, translation_error = transform_errors(right.transformation, item["transform"])
    assert rotation_error < 2.0 and translation_error < 0.05
    assert right.confidence > wrong.confidence
