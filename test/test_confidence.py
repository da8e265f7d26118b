"""The calibrated confidence: every shipped model carries a calibration fitted for it, and its probability
separates right from wrong poses on held-out pairs (ground-truth poses as the truth): consecutive frames
score high, clouds of two different buildings score low."""

from __future__ import annotations

import json
import math
import warnings

import numpy as np
import pytest

from genreg_core.checkpoint import resolve_checkpoint
from genreg_core.confidence import (
    FEATURES,
    FEATURES_OF,
    MAP_CALIBRATION,
    SEE_THROUGH_FLOOR,
    ConfidenceModel,
    calibration_path,
    features,
    load_beside,
    map_features,
)
from genreg_core.config import SCENE_REGISTRATION, RefineConfig
from genreg_core.data import FramePairs, RGBDSequence
from genreg_core.errors import CheckpointError, UncalibratedWarning
from genreg_core.metrics import transform_errors
from genreg_core.registration import Registrar

SHIPPED = ("modelnet40", "modelnet40_dgcnn", "modelnet40_partial", "7scenes")


@pytest.mark.parametrize("name", SHIPPED)
def test_every_shipped_model_has_its_own_calibration(name):
    model = load_beside(resolve_checkpoint(name))
    assert model is not None and model.features == FEATURES
    assert Registrar.from_checkpoint(name).calibration == model
    assert model.by_refinement  # every refinement it serves: a well-seated pose against one that overlaps nothing
    for method in set(model.by_refinement) - set(FEATURES_OF):
        assert model.probability(features([0.9, 0.97, 0.99, 1.0], 0.6, 1.0), method) > 0.8
        assert model.probability(features([0.01, 0.03, 0.05, 0.1], 0.01, 1.0), method) < 0.1
    if MAP_CALIBRATION in model.by_refinement:  # registrations that see through the map or not
        assert model.probability(map_features(0.97, 0.01), MAP_CALIBRATION) > 0.8
        assert model.probability(map_features(0.7, 0.01), MAP_CALIBRATION) > 0.5
        assert model.probability(map_features(0.7, 0.2), MAP_CALIBRATION) < 0.5  # a slide seen in training
        assert model.probability(map_features(0.05, 0.01), MAP_CALIBRATION) < 0.1
        # a whole-map pose that sees through nothing because it puts little of the scan on the map: seen in
        # training at registration probabilities of 0.2-0.3, judged 0.8 before the see-through floor
        assert model.probability(map_features(0.25, 0.0), MAP_CALIBRATION) < 0.5
        assert np.array_equal(map_features(0.25, 0.0), map_features(0.25, SEE_THROUGH_FLOOR))


def test_a_calibration_serves_only_its_checkpoint_and_its_features(tmp_path):
    other = resolve_checkpoint("modelnet40_dgcnn")
    with pytest.raises(CheckpointError, match="another checkpoint"):
        ConfidenceModel.load(calibration_path(resolve_checkpoint("7scenes")), other)
    values = json.loads(calibration_path(resolve_checkpoint("7scenes")).read_text())
    (tmp_path / "bad.json").write_text(json.dumps({**values, "features": ["fitness"]}))
    with pytest.raises(CheckpointError, match="features"):
        ConfidenceModel.load(tmp_path / "bad.json")


@pytest.fixture(scope="module")
def scene_registrar() -> Registrar:
    return Registrar.from_checkpoint("7scenes", SCENE_REGISTRATION)


def test_consecutive_validation_frames_are_confident_and_right(scene_registrar):
    pairs = FramePairs(RGBDSequence.redkitchen(), 3, range(900, 1000))
    for index in np.linspace(0, len(pairs) - 1, 6).astype(int):
        item = pairs[int(index)]
        result = scene_registrar.register(item["source"][::4], item["target"][::4])
        rotation_error, translation_error = transform_errors(result.transformation, item["transform"])
        assert rotation_error < 2.0 and translation_error < 0.05
        assert result.confidence > 0.8, result.verification


def test_clouds_of_two_different_places_are_not_confident(scene_registrar):
    """A redkitchen validation frame against SUN3D frames (another building): no pose is right."""
    kitchen, sun3d = RGBDSequence.redkitchen(), RGBDSequence.sun3d(1)
    for i, j in ((850, 940), (900, 960), (950, 980)):
        result = scene_registrar.register(kitchen.points(i)[::4], sun3d.points(j)[::4])
        assert result.confidence < 0.5, result.verification


def test_a_calibration_serves_only_the_refinements_it_was_fitted_for(scene_registrar):
    """Results refined otherwise are on another scale: the registrar warns when it is built (and when its
    settings change to such a refinement, not when other settings change) and they get the uncalibrated
    overlap score."""
    import dataclasses

    from genreg_core.score import overlap_score

    calibration = scene_registrar.calibration
    assert calibration.serves("gicp") and scene_registrar.calibrated
    other = dataclasses.replace(SCENE_REGISTRATION, refine=dataclasses.replace(SCENE_REGISTRATION.refine,
                                                                                method="point_to_point"))
    only_gicp = dataclasses.replace(calibration, by_refinement={"gicp": calibration.by_refinement["gicp"]})
    with pytest.warns(UncalibratedWarning, match="no model for refine.method 'point_to_point' \\(it has gicp\\)"):
        unserved = Registrar(scene_registrar.model, other, only_gicp)
    seq = RGBDSequence.redkitchen()
    result = unserved.register(seq.points(900)[::4], seq.points(903)[::4])
    assert not unserved.calibrated
    constraint = math.exp(result.verification["log_constraint"])
    assert result.confidence == pytest.approx(
        constraint * overlap_score(result.fitness, result.tight_fitness, result.inlier_ratio), rel=1e-6)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        unserved.config = dataclasses.replace(other, passes=2)  # the same refinement: no new warning
        unserved.config = SCENE_REGISTRATION  # a served one
    assert unserved.calibrated
    with pytest.warns(UncalibratedWarning, match="'none'"):
        unserved.config = dataclasses.replace(other, refine=RefineConfig(method="none"))
    with pytest.warns(UncalibratedWarning, match="no confidence calibration"):
        Registrar(scene_registrar.model, SCENE_REGISTRATION)
