"""Calibrated cameras: refine(..., D=...) sees through the lens distortion what a pinhole camera would.

The distorted frames are made from a shipped sample frame (a pinhole render) with OpenCV's own distortion model:
each raw pixel shows what the pinhole image has at its undistorted position (cv2.undistortPoints), and each box is
the raw image's box whose sides pass through the distorted midpoints of the pinhole box's sides.
"""

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from refiner_rt import RefinerSession, RefinerTracker
from refiner_rt import quaternion as rq
from refiner_rt.distortion import crop_undistorted, undistort_boxes, validate_D
from refiner_rt.preprocess import crop_to_square

SAMPLES = Path(__file__).resolve().parents[1] / "refiner_rt" / "samples"
PLUMB_BOB = np.array([-1.2, 1.0, 0.002, -0.003, 0.0])  # strong barrel distortion at this narrow lens
RATIONAL = np.array([2.0, -0.5, 0.001, 0.0, 0.05, 3.0, -0.1, 0.1])


def _frame():
    doc = json.loads((SAMPLES / "samples.json").read_text())
    f = doc["frames"][0]
    return cv2.imread(str(SAMPLES / f["file"])), np.array(f["K"]), f["objects"]


def _distort_image(image, K, D):
    h, w = image.shape[:2]
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
    pts = np.stack([xs.ravel(), ys.ravel()], 1).reshape(-1, 1, 2)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 40, 1e-10)
    und = (cv2.undistortPointsIter(pts, K, D, None, K, crit) if hasattr(cv2, "undistortPointsIter")
           else cv2.undistortPoints(pts, K, D, None, None, K, crit))
    und = und.reshape(h, w, 2).astype(np.float32)
    return cv2.remap(image, und[..., 0], und[..., 1], cv2.INTER_LINEAR)


def _distort_box(box, K, D):
    x1, y1, x2, y2 = box
    cx, cy = (x1 + x2) / 2, (y1 + y2) / 2
    mids = np.array([[x1, cy], [cx, y1], [x2, cy], [cx, y2]]) - 0.5
    rays = np.stack([(mids[:, 0] - K[0, 2]) / K[0, 0], (mids[:, 1] - K[1, 2]) / K[1, 1], np.ones(4)], 1)
    raw, _ = cv2.projectPoints(rays.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K, D)
    raw = raw.reshape(-1, 2) + 0.5
    return np.array([max(raw[0, 0], 0.0), max(raw[1, 1], 0.0), raw[2, 0], raw[3, 1]])


@pytest.mark.parametrize("D", [PLUMB_BOB, RATIONAL], ids=["plumb_bob", "rational_polynomial"])
def test_a_distorted_frame_refines_like_the_pinhole_frame(D):
    image, K, objects = _frame()
    raw = _distort_image(image, K, D)
    rng = np.random.default_rng(0)
    with_d, without_d, crop_with, crop_without = [], [], [], []
    for o in objects:
        sess = RefinerSession.pretrained(o["object_id"])
        box = np.array(o["box_xyxy"], float)
        box_raw = _distort_box(box, K, D)
        q_in = rq.multiply(np.array(o["q_gt_wxyz"]), rq.from_axis_angle(rng.normal(size=3), 15.0))[None]
        pinhole = sess.refine(image, box[None], q_in, K=K).q_refined
        through = sess.refine(raw, box_raw[None], q_in, K=K, D=D).q_refined
        ignored = sess.refine(raw, box_raw[None], q_in, K=K).q_refined
        with_d.append(rq.geodesic_angle(pinhole, through)[0])
        without_d.append(rq.geodesic_angle(pinhole, ignored)[0])
        np.testing.assert_allclose(undistort_boxes(box_raw[None], K, D)[0], box, atol=1.0)
        ref = crop_to_square(image, box, 64, 1.2).astype(float)
        crop_with.append(np.abs(crop_undistorted(raw, box, 64, 1.2, K, D).astype(float) - ref).mean())
        crop_without.append(np.abs(crop_to_square(raw, box_raw, 64, 1.2).astype(float) - ref).mean())
    # The crops through the distortion are the pinhole crops up to resampling; cut straight from the raw frame
    # they are bent, and the refined rotations move with them.
    assert np.mean(crop_with) < 1.0 and np.mean(crop_with) < 0.3 * np.mean(crop_without)
    assert np.mean(with_d) < 0.8, with_d
    assert np.mean(without_d) > 2.5 * np.mean(with_d), (with_d, without_d)


def test_zero_or_no_distortion_is_the_pinhole_path():
    image, K, objects = _frame()
    o = objects[0]
    sess = RefinerSession.pretrained(o["object_id"])
    box, q = np.array([o["box_xyxy"]], float), np.array([o["q_gt_wxyz"]])
    plain = sess.refine(image, box, q, K=K).q_refined
    np.testing.assert_array_equal(sess.refine(image, box, q, K=K, D=np.zeros(5)).q_refined, plain)
    assert validate_D(None) is None and validate_D([0.0] * 8) is None


def test_the_tracker_takes_distortion():
    image, K, objects = _frame()
    o = objects[0]
    raw = _distort_image(image, K, PLUMB_BOB)
    box_raw = _distort_box(np.array(o["box_xyxy"], float), K, PLUMB_BOB)
    q0 = np.array(o["q_gt_wxyz"])
    sess = RefinerSession.pretrained(o["object_id"])
    tracker = RefinerTracker(sess, K, {o["object_id"]: q0}, D=PLUMB_BOB)
    got = tracker.update(raw, {o["object_id"]: box_raw})[o["object_id"]]
    want = sess.refine(raw, box_raw[None], q0[None], K=K, D=PLUMB_BOB).q_refined[0]
    np.testing.assert_allclose(got, want, atol=1e-9)


@pytest.mark.parametrize("D, message", [
    ([0.1, 0.2, 0.3], "4, 5, 8, 12 or 14 numbers"),
    ([0.1, float("nan"), 0, 0, 0], "finite"),
    ("plumb_bob", "4, 5, 8, 12 or 14 numbers"),
    (np.zeros((2, 2, 2)), "4, 5, 8, 12 or 14 numbers"),
])
def test_bad_distortion_is_named(D, message):
    image, K, objects = _frame()
    sess = RefinerSession.pretrained(objects[0]["object_id"])
    with pytest.raises(ValueError, match="D must") as info:
        sess.refine(image, np.array([objects[0]["box_xyxy"]], float), np.array([[1.0, 0, 0, 0]]), K=K, D=D)
    assert message in str(info.value)


def test_distortion_needs_K():
    image, K, objects = _frame()
    sess = RefinerSession.pretrained(objects[0]["object_id"])
    with pytest.raises(ValueError, match="K is required with D"):
        sess.refine(image, np.array([objects[0]["box_xyxy"]], float), np.array([[1.0, 0, 0, 0]]), D=PLUMB_BOB)
