"""Box errors of matched detections (radaredge.eval.box_errors): nuScenes' centre-distance
matching in descending score, the signed height bias and the other errors in radar-frame units."""

import math

import numpy as np
import pytest

from radaredge.eval.box_errors import MATCH_DISTANCE, box_error_lines, class_box_errors, match_frame


def box(x, y, z=0.0, l=4.0, w=1.8, h=1.5, yaw=0.0):
    return [x, y, z, l, w, h, yaw]


def test_detections_take_the_nearest_free_box_in_score_order():
    gt = np.array([box(10, 0), box(11.5, 0), box(30, 0)])
    dt = np.array([box(11, 0), box(10.2, 0), box(30 + MATCH_DISTANCE + 0.1, 0)])
    # the first detection takes the nearer box (0.5 m away, not the one 1.0 m away), the second
    # the one left, the third lies beyond the match distance of the third box
    assert match_frame(dt, gt) == [(0, 1), (1, 0)]


def test_errors_are_signed_for_height_and_absolute_for_the_rest():
    gt = np.array([box(10, 0, z=-0.3), box(20, 5, z=-0.5, yaw=3.0)])
    dt = np.array([box(10.3, 0.4, z=0.1, h=1.9), box(20, 5, z=0.1, l=3.0, yaw=-3.0)])
    e = class_box_errors([(dt, np.array([0.9, 0.8]), gt)])
    assert (e.ground_truth, e.matched) == (2, 2)
    assert e.xy == pytest.approx((0.5 + 0.0) / 2)
    assert e.dz == pytest.approx((0.4 + 0.6) / 2) and e.abs_dz == pytest.approx(0.5)
    assert e.abs_dh == pytest.approx(0.2) and e.abs_dl == pytest.approx(0.5) and e.abs_dw == pytest.approx(0.0)
    assert e.heading_deg == pytest.approx(math.degrees(2 * math.pi - 6.0) / 2)  # wrapped across +-pi
    assert e.dz > 0  # boxes sit too high


def test_frames_are_matched_apart_and_an_empty_class_gives_nan():
    frames = [
        (np.array([box(10, 0)]), np.array([0.5]), np.zeros((0, 7))),
        (np.zeros((0, 7)), np.zeros(0), np.array([box(10, 0)])),
    ]
    e = class_box_errors(frames)
    assert (e.ground_truth, e.matched) == (1, 0) and math.isnan(e.xy) and e.to_dict()["xy"] is None
    assert "0/1" in box_error_lines({"onnxruntime": {"Car": e}})[1]
