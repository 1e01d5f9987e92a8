"""The calibrated volume: hull of the DOE points, signed distance, margin, persistence."""
import numpy as np
import pytest

from dt_kernel.errors import DataError, ModelError
from dt_runtime.frames.volume import CalibratedVolume

BOX = np.array([[x, y, z] for x in (0.0, 0.4) for y in (-0.2, 0.2) for z in (0.3, 0.6)])


def test_signed_distance_of_a_box():
    v = CalibratedVolume.of_points(BOX)
    d = v.distance(np.array([[0.2, 0.0, 0.45], [0.5, 0.0, 0.45], [0.2, 0.0, 0.75], [0.39, 0.0, 0.45]]))
    assert d == pytest.approx([-0.15, 0.1, 0.15, -0.01], abs=1e-12)


def test_margin_widens_what_counts_as_inside():
    P = np.array([[0.45, 0.0, 0.45], [0.55, 0.0, 0.45]])
    assert CalibratedVolume.of_points(BOX).inside(P).tolist() == [False, False]
    assert CalibratedVolume.of_points(BOX, margin_m=0.08).inside(P).tolist() == [True, False]


def test_round_trip_and_bad_input():
    v = CalibratedVolume.of_points(BOX, 0.05)
    w = CalibratedVolume.from_dict(v.to_dict())
    P = np.random.default_rng(0).uniform(-0.5, 1.0, (50, 3))
    assert np.array_equal(v.distance(P), w.distance(P)) and w.margin_m == 0.05
    with pytest.raises(DataError, match="do not span a volume"):
        CalibratedVolume.of_points(BOX[BOX[:, 2] == 0.3])  # a plane
    with pytest.raises(DataError, match="margin"):
        CalibratedVolume.of_points(BOX, margin_m=-1)
    with pytest.raises(ModelError, match="needs normals"):
        CalibratedVolume.from_dict({"normals": [[1, 0, 0]]})
