"""RefinerTracker against constant-output test models (tests/onnx_fixtures.py) and SciPy's Rotation: the previous
refined rotation as the next coarse pose, batching per session, the constant-velocity prediction, objects coming
and going, and the errors."""


import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from refiner_rt import RefineResult, RefinerSession
from refiner_rt import RefinerTracker
from refiner_rt import quaternion as rq
from refiner_rt.tracker import DEFAULT_HOLD_MAX_CORRECTION_DEG
from tests import onnx_fixtures as fx
from tests.test_pretrained import weights  # noqa: F401  (the made-up shipped models)

RNG = np.random.default_rng(0)
IMG = RNG.integers(0, 256, (48, 64, 3), dtype=np.uint8)
K = np.array([[60.0, 0.0, 31.5], [0.0, 60.0, 23.5], [0.0, 0.0, 1.0]])
BOX_A = [5.0, 6.0, 25.0, 30.0]
BOX_B = [30.5, 10.0, 60.0, 40.0]
Q_OUT = rq.from_axis_angle([0.2, -0.4, 0.9], 7.0)  # every update multiplies by this
Q0 = rq.normalize(rq.from_xyzw(Rotation.random(2, random_state=3).as_quat()))  # w >= 0



def _result(q_refined) -> RefineResult:
    """A RefineResult of fake refinements: ``q_refined`` as given, no correction measured (score 1)."""
    q = np.asarray(q_refined, dtype=np.float64)
    identity = np.tile([1.0, 0.0, 0.0, 0.0], (len(q), 1))
    return RefineResult(q_refined=q, q_out=identity, q_in=q)


# the share of the constant model's 7-degree correction the default filter keeps after the first update (3 degrees)
HELD = DEFAULT_HOLD_MAX_CORRECTION_DEG / 7.0
# the exact algebra of the updates, without the default temporal filter (which holds each correction to 3 degrees)
NO_FILTER = dict(prediction_weight=0.0, max_correction_deg=180.0)


def _unfiltered(*args, **kwargs) -> RefinerTracker:
    """A RefinerTracker without the temporal filter, unless the test gives its own prediction settings."""
    if kwargs.get("predict") in (None, False):
        kwargs = {**NO_FILTER, **kwargs}
    return RefinerTracker(*args, **kwargs)

def scipy_q(q_wxyz):
    return Rotation.from_quat(rq.to_xyzw(q_wxyz))


def session(q_out=Q_OUT, objects=("003_cracker_box",), frame="camera"):
    props = fx.contract(objects=list(objects), rotation_frame=frame)
    return RefinerSession(fx.constant_model(q_out, props=props))


def assert_same_rotation(q, rotation: Rotation, atol=1e-6):
    np.testing.assert_allclose(rq.to_matrix(q), rotation.as_matrix(), atol=atol)


@pytest.mark.parametrize("frame", ["camera", "ray"])
def test_each_update_refines_the_previous_result(frame):
    """After n updates with a model whose correction is always c: q = q0 * c^n (either model frame)."""
    tracker = _unfiltered(session(frame=frame), K, {"003_cracker_box": Q0[0]})
    for n in range(1, 6):
        q = tracker.update(IMG, {"003_cracker_box": BOX_A})["003_cracker_box"]
        ref = scipy_q(Q0[0]) * scipy_q(Q_OUT) ** n
        assert_same_rotation(q, ref)
        assert q.shape == (4,) and q.dtype == np.float64 and q[0] >= 0
        assert_same_rotation(tracker.rotations["003_cracker_box"], ref)


@pytest.mark.parametrize("kwargs, share", [(dict(prediction_weight=0.4, max_correction_deg=180.0), 0.6),
                                           (dict(max_correction_deg=2.8), 0.4),
                                           (dict(prediction_weight=0.5, max_correction_deg=2.8), 0.4),
                                           (dict(), 3.0 / 7.0)])
def test_the_temporal_filter_without_prediction_holds_back_each_correction(kwargs, share):
    """With no motion prediction the last rotation is the prediction: from the second update on, a constant 7-degree
    correction c is kept at (1 - prediction_weight) of its angle, at most max_correction_deg: q = q0 c c^(share (n-1));
    the first update, from the coarse start, is kept whole."""
    tracker = RefinerTracker(session(), K, {"003_cracker_box": Q0[0]}, **kwargs)
    for n in range(1, 5):
        q = tracker.update(IMG, {"003_cracker_box": BOX_A})["003_cracker_box"]
        assert_same_rotation(q, scipy_q(Q0[0]) * scipy_q(Q_OUT) * scipy_q(Q_OUT) ** (share * (n - 1)))


def test_objects_sharing_a_session_are_refined_in_one_call(monkeypatch):
    shared = session(objects=("003_cracker_box", "011_banana"))
    other = session(q_out=rq.identity(), objects=("004_sugar_box",))
    calls = []
    for s, label in ((shared, "shared"), (other, "other")):
        real = s.refine

        def spy(image, boxes, q_in, _real=real, _label=label, **kw):
            calls.append((_label, np.asarray(boxes).shape, np.asarray(q_in).copy()))
            return _real(image, boxes, q_in, **kw)

        monkeypatch.setattr(s, "refine", spy)
    q0 = {"003_cracker_box": Q0[0], "011_banana": Q0[1], "004_sugar_box": rq.identity()}
    tracker = RefinerTracker({"003_cracker_box": shared, "011_banana": shared, "004_sugar_box": other}, K, q0)
    out = tracker.update(IMG, {"003_cracker_box": BOX_A, "011_banana": BOX_B, "004_sugar_box": BOX_A})
    assert sorted((c[0], c[1]) for c in calls) == [("other", (1, 4)), ("shared", (2, 4))]
    shared_q_in = next(c[2] for c in calls if c[0] == "shared")
    np.testing.assert_allclose(shared_q_in, np.stack([Q0[0], Q0[1]]), atol=1e-12)
    assert_same_rotation(out["003_cracker_box"], scipy_q(Q0[0]) * scipy_q(Q_OUT))
    assert_same_rotation(out["011_banana"], scipy_q(Q0[1]) * scipy_q(Q_OUT))
    assert_same_rotation(out["004_sugar_box"], Rotation.identity())


def test_a_missed_object_keeps_its_rotation_and_others_move_on():
    shared = session(objects=("003_cracker_box", "011_banana"))
    tracker = _unfiltered(shared, K, {"003_cracker_box": Q0[0], "011_banana": Q0[1]})
    out = tracker.update(IMG, {"011_banana": BOX_B})
    assert list(out) == ["011_banana"]
    np.testing.assert_array_equal(tracker.rotations["003_cracker_box"], rq.normalize(Q0[0]))
    tracker.update(IMG, {"003_cracker_box": BOX_A, "011_banana": BOX_B})
    assert_same_rotation(tracker.rotations["003_cracker_box"], scipy_q(Q0[0]) * scipy_q(Q_OUT))
    assert_same_rotation(tracker.rotations["011_banana"], scipy_q(Q0[1]) * scipy_q(Q_OUT) ** 2)


def prediction_reference(q0: Rotation, c: Rotation, seen: list[bool]) -> Rotation:
    """The constant-angular-velocity tracker written out with SciPy: after a refined-to-refined step over k updates
    the velocity is (q_t q_prev^-1)^(1/k); the coarse pose is velocity^(missed + 1) * q before each refinement."""
    q, refined, velocity, missed = q0, False, None, 0
    for s in seen:
        if not s:
            missed += 1
            continue
        q_in = q if velocity is None else Rotation.from_rotvec(velocity.as_rotvec() * (missed + 1)) * q
        q_new = q_in * c
        if refined:
            velocity = Rotation.from_rotvec((q_new * q.inv()).as_rotvec() / (missed + 1))
        q, refined, missed = q_new, True, 0
    return q


@pytest.mark.parametrize("seen", [[True] * 6, [True, True, False, True, False, False, True, True]])
def test_constant_velocity_prediction_matches_a_scipy_reference(seen):
    c = rq.from_axis_angle([0.0, 0.3, 1.0], 4.0)
    tracker = RefinerTracker(session(q_out=c), K, {"003_cracker_box": Q0[0]}, predict=True)
    for s in seen:
        tracker.update(IMG, {"003_cracker_box": BOX_A} if s else {})
    assert_same_rotation(tracker.rotations["003_cracker_box"], prediction_reference(scipy_q(Q0[0]), scipy_q(c), seen))


def scene_reference(q0: dict, c: Rotation, seen: list[set], window: int, weight: float, max_deg: float = 2.0,
                    trimmed=None) -> dict:
    """The scene-motion tracker written out with SciPy: the turn per update is the mean over tracks of each one's
    change across the refiner's results of the last ``window`` updates (spans of at least ``window // 2``; with
    three or more, those further from the medoid than 0.2 degrees and twice the median left out); every refined
    track is turned by it before the update, and once a turn is measured a refined one keeps ``weight`` of the
    prediction and stays within ``max_deg`` of it."""
    q, refined, hist = dict(q0), {k: False for k in q0}, {k: [] for k in q0}
    trimmed = [] if trimmed is None else trimmed  # how many tracks each turn left out
    for t, objs in enumerate(seen):
        rates = []
        for h in hist.values():
            h = [(u, r) for u, r in h if t - u <= window]
            if len(h) >= 2 and h[-1][0] - h[0][0] >= max(1, window // 2):
                rates.append(Rotation.from_rotvec((h[-1][1] * h[0][1].inv()).as_rotvec() / (h[-1][0] - h[0][0])))
        if len(rates) >= 3:  # tracks far from the others left out
            apart = np.degrees([[(a * b.inv()).magnitude() for b in rates] for a in rates])
            off = apart[np.argmin(apart.sum(axis=1))]
            kept = [r for r, o in zip(rates, off) if o <= max(0.2, 2 * np.median(off))]
            trimmed.append(len(rates) - len(kept))
            rates = kept
        turn = Rotation.concatenate(rates).mean() if rates else None
        for k in q:
            predicted = turn is not None and refined[k]
            p = turn * q[k] if predicted else q[k]
            if k not in objs:
                q[k] = p
                continue
            r = p * c
            new = r
            if predicted:
                new = Rotation.from_rotvec((p * r.inv()).as_rotvec() * weight) * r
                step = new * p.inv()
                if np.degrees(step.magnitude()) > max_deg:
                    new = Rotation.from_rotvec(step.as_rotvec() * max_deg / np.degrees(step.magnitude())) * p
            hist[k] = [(u, x) for u, x in hist[k] if t - u < window] + [(t, r)]
            q[k], refined[k] = new, True
    return q


@pytest.mark.parametrize("window,weight,max_deg,three", [(4, 0.0, 180.0, False), (4, 0.3, None, False),
                                                          (6, 0.5, 1.0, False), (4, 0.3, None, True)])
def test_scene_prediction_matches_a_scipy_reference(window, weight, max_deg, three):
    c = rq.from_axis_angle([0.0, 0.3, 1.0], 4.0)
    shared = session(q_out=c, objects=("003_cracker_box", "011_banana"))
    q0 = {"003_cracker_box": Q0[0], "011_banana": Q0[1]}
    both = {"003_cracker_box", "011_banana"}
    if three:  # two tracks that turn alike and one that does not: the turn leaves that one out
        q0 = {"003_cracker_box": Q0[0], "011_banana": rq.multiply(rq.from_axis_angle([1.0, 0.0, 0.0], 2.0), Q0[0]),
              "011_banana#2": Q0[1]}
        both = set(q0)
    seen = [both] * 5 + [{"011_banana"}] * 4 + [{"003_cracker_box"}, set()] + [both] * 3
    tracker = RefinerTracker(shared, K, q0, predict="scene", motion_window=window, prediction_weight=weight,
                             max_correction_deg=max_deg)
    boxes = {"003_cracker_box": BOX_A, "011_banana": BOX_B, "011_banana#2": BOX_B}
    for objs in seen:
        tracker.update(IMG, {k: boxes[k] for k in objs})
    trimmed = []
    ref = scene_reference({k: scipy_q(v) for k, v in q0.items()}, scipy_q(c), seen, window, weight,
                          2.0 if max_deg is None else max_deg, trimmed)
    assert (max(trimmed, default=0) > 0) == three  # the three-track case does leave one out
    for k in q0:
        assert_same_rotation(tracker.rotations[k], ref[k])


def test_scene_prediction_carries_a_hidden_object_with_the_camera(monkeypatch):
    """A camera turning 3 degrees per update over two still objects and a refiner that returns the truth: with the
    scene's motion the object hidden for ten updates comes back where the camera took it; without, 30 degrees off."""
    turn = rq.from_axis_angle([0.3, 1.0, -0.2], 3.0)

    def truth(q0, t):
        return rq.multiply(rq.from_axis_angle([0.3, 1.0, -0.2], 3.0 * t), q0) if t else q0

    shared = session(objects=("003_cracker_box", "011_banana"))
    clock, inputs = {"t": 0}, {}

    def perfect(image, boxes, q_in, **kw):
        a = [np.allclose(b, BOX_A) for b in np.asarray(boxes)]
        for is_a, q in zip(a, q_in):
            inputs[clock["t"], is_a] = np.array(q)
        return _result(np.array([truth(Q0[0] if is_a else Q0[1], clock["t"]) for is_a in a]))

    monkeypatch.setattr(shared, "refine", perfect)
    assert rq.geodesic_angle(turn, rq.identity()) == pytest.approx(3.0)
    for predict in ("scene", False):
        tracker = RefinerTracker(shared, K, {"003_cracker_box": Q0[0], "011_banana": Q0[1]}, predict=predict,
                                 prediction_weight=0.0)
        inputs.clear()
        for t in range(18):
            clock["t"] = t
            hidden = 5 <= t < 15
            tracker.update(IMG, {"011_banana": BOX_B} if hidden else {"003_cracker_box": BOX_A, "011_banana": BOX_B})
            if predict == "scene" and hidden and t >= 7:  # once the turn is measured, the hidden track follows it
                assert rq.geodesic_angle(tracker.rotations["003_cracker_box"], truth(Q0[0], t)) < 1e-6
        back = rq.geodesic_angle(inputs[15, True], truth(Q0[0], 15))
        if predict == "scene":
            assert back < 1e-6
        else:
            assert back == pytest.approx(33.0, abs=1e-6)  # held since update 4: 11 turns of 3 degrees


def test_scene_prediction_follows_a_camera_that_starts_to_turn(monkeypatch):
    """A still camera that starts turning 8 degrees per update, a refiner that returns the truth, the defaults: the
    turn is measured from the refiner's results (not from the damped, limited rotations), so the tracks stay within
    reach of the refiner while it catches up and then follow exactly."""
    axis = [0.3, 1.0, -0.2]

    def truth(q0, t):  # still for 5 updates, then 8 degrees per update
        return rq.multiply(rq.from_axis_angle(axis, 8.0 * max(0, t - 5)), q0)

    shared = session(objects=("003_cracker_box", "011_banana"))
    clock = {"t": 0}

    def perfect(image, boxes, q_in, **kw):
        return _result(np.array([truth(Q0[0] if np.allclose(b, BOX_A) else Q0[1], clock["t"])
                                                   for b in np.asarray(boxes)]))

    monkeypatch.setattr(shared, "refine", perfect)
    tracker = RefinerTracker(shared, K, {"003_cracker_box": Q0[0], "011_banana": Q0[1]}, predict="scene")
    errors = []
    for t in range(30):
        clock["t"] = t
        out = tracker.update(IMG, {"003_cracker_box": BOX_A, "011_banana": BOX_B})
        errors.append(rq.geodesic_angle(out["003_cracker_box"], truth(Q0[0], t)))
    assert max(errors) < 15.0  # within the refiner's 30-degree reach throughout
    assert max(errors[-5:]) < 1e-3


def test_scene_prediction_starts_reset_and_added_tracks_from_the_pose_given(monkeypatch):
    """A reset or newly added track is a coarse start: its first update refines the pose given, not that pose turned
    by the scene's turn; its next update is predicted from the refiner's result like the others."""
    axis = [0.0, 0.6, 0.8]

    def truth(q0, t):  # the camera turns 3 degrees per update
        return rq.multiply(rq.from_axis_angle(axis, 3.0 * t), q0) if t else q0

    shared = session(objects=("003_cracker_box", "011_banana"))
    clock, inputs = {"t": 0}, {}
    start = {"003_cracker_box": Q0[0], "011_banana": Q0[1]}

    def perfect(image, boxes, q_in, **kw):
        ids = ["003_cracker_box" if np.allclose(b, BOX_A) else "011_banana" for b in np.asarray(boxes)]
        inputs.update({(clock["t"], i): np.array(q) for i, q in zip(ids, q_in)})
        return _result(np.array([truth(start[i], clock["t"]) for i in ids]))

    monkeypatch.setattr(shared, "refine", perfect)
    tracker = RefinerTracker(shared, K, {"003_cracker_box": Q0[0]}, predict="scene", prediction_weight=0.0)
    both = {"003_cracker_box": BOX_A, "011_banana": BOX_B}
    coarse = rq.from_axis_angle([1.0, 0.0, 0.0], 20.0)
    for t in range(12):
        clock["t"] = t
        if t == 4:
            tracker.add("011_banana", coarse)
        if t == 8:
            tracker.reset("003_cracker_box", coarse)
        tracker.update(IMG, both if t >= 4 else {"003_cracker_box": BOX_A})
    for t, object_id in ((4, "011_banana"), (8, "003_cracker_box")):
        np.testing.assert_allclose(inputs[t, object_id], coarse, atol=1e-12)  # the pose given, as given
        assert rq.geodesic_angle(inputs[t + 1, object_id], truth(start[object_id], t + 1)) < 1e-6  # then predicted
    tracker.drop("011_banana")
    clock["t"] = 12
    tracker.update(IMG, {"003_cracker_box": BOX_A})
    assert rq.geodesic_angle(inputs[12, "003_cracker_box"], truth(Q0[0], 12)) < 1e-6


def test_reset_forgets_the_motion():
    """A detector's pose after a reset is coarse: the jump to it is not motion, so nothing is predicted from it."""
    tracker = RefinerTracker(session(q_out=rq.identity()), K, {"003_cracker_box": Q0[0]}, predict=True)
    tracker.update(IMG, {"003_cracker_box": BOX_A})  # refined: q0 (the identity correction)
    tracker.reset("003_cracker_box", rq.multiply(rq.from_axis_angle([1.0, 1.0, 0.0], 20.0), Q0[0]))
    before = tracker.update(IMG, {"003_cracker_box": BOX_A})["003_cracker_box"]
    after = tracker.update(IMG, {"003_cracker_box": BOX_A})["003_cracker_box"]
    np.testing.assert_allclose(after, before, atol=1e-12)


def test_reset_add_and_drop():
    shared = session(objects=("003_cracker_box", "011_banana"))
    tracker = RefinerTracker(shared, K, {"003_cracker_box": Q0[0]})
    tracker.update(IMG, {"003_cracker_box": BOX_A})
    tracker.reset("003_cracker_box", [2.0, 0.0, 0.0, 0.0])  # not unit: normalised
    np.testing.assert_array_equal(tracker.rotations["003_cracker_box"], [1.0, 0.0, 0.0, 0.0])
    tracker.add("011_banana#2", Q0[1])
    assert tracker.object_ids == ["003_cracker_box", "011_banana#2"] and len(tracker) == 2 and "011_banana#2" in tracker
    out = tracker.update(IMG, {"011_banana#2": BOX_B, "003_cracker_box": BOX_A})
    assert_same_rotation(out["011_banana#2"], scipy_q(Q0[1]) * scipy_q(Q_OUT))
    assert_same_rotation(out["003_cracker_box"], scipy_q(Q_OUT))
    tracker.drop("003_cracker_box")
    assert tracker.object_ids == ["011_banana#2"]
    with pytest.raises(ValueError, match=r"boxes names '003_cracker_box', which is not tracked \(tracked: \['011_banana#2'\]\)"):
        tracker.update(IMG, {"003_cracker_box": BOX_A})


def test_pretrained_names_load_once_and_are_shared(weights):  # noqa: F811
    tracker = RefinerTracker({"003_cracker_box": "003_cracker_box", "003_cracker_box#2": "003_cracker_box",
                              "011_banana": "011_banana"}, K,
                             {"003_cracker_box": Q0[0], "003_cracker_box#2": Q0[1], "011_banana": Q0[0]})
    sessions = {k: t.session for k, t in tracker._tracks.items()}
    assert sessions["003_cracker_box"] is sessions["003_cracker_box#2"]
    assert sessions["011_banana"] is not sessions["003_cracker_box"]
    assert sessions["011_banana"].model_path == weights / "011_banana.int8.onnx"
    single = RefinerTracker("011_banana", K, {"011_banana": Q0[0]})
    out = single.update(IMG, {"011_banana": BOX_A})  # the made-up models output the identity correction
    assert_same_rotation(out["011_banana"], scipy_q(Q0[0]))


@pytest.mark.parametrize("kwargs, error, match", [
    (dict(K=np.eye(2)), ValueError, r"K must be a \(3, 3\) numeric intrinsics matrix"),
    (dict(K=[[0, 0, 1], [0, 60, 1], [0, 0, 1]]), ValueError, "fx > 0"),
    (dict(q0=[1, 0, 0, 0]), TypeError, r"q0 must be a mapping \{object id: \(4,\) wxyz rotation\}"),
    (dict(q0={"003_cracker_box": [0, 0, 0, 0]}), ValueError, r"q0\['003_cracker_box'\] must be non-zero"),
    (dict(q0={"003_cracker_box": [1, 0, 0]}), ValueError, r"q0\['003_cracker_box'\] must have shape \(\.\.\., 4\)"),
    (dict(q0={"003_cracker_box": [[1, 0, 0, 0]]}), ValueError, r"q0\['003_cracker_box'\] must be one rotation: a \(4,\) quaternion \(wxyz\) or a \(3, 3\) matrix"),
    (dict(q0={"003_cracker_box": [1, np.nan, 0, 0]}), ValueError, r"q0\['003_cracker_box'\] must be finite"),
    (dict(q0={"011_banana": [1, 0, 0, 0]}), ValueError,
     r"object_id '011_banana' is not an object its session's model was trained for \(metadata objects: \['003_cracker_box'\]\)"),
    (dict(q0={3: [1, 0, 0, 0]}), TypeError, "object ids must be non-empty strings"),
    (dict(session=3), TypeError, "session must be a RefinerSession, a RefinerCascade or a pretrained model name"),
    (dict(predict="yes"), ValueError, "predict must be False, True, .object. or .scene."),
    (dict(predict=None), TypeError, "predict must be False, True, .object. or .scene."),
    (dict(motion_window=8), ValueError, "motion_window=8 is the window of the scene's turn; it needs predict='scene'"),
    (dict(predict="scene", motion_window=4.0), TypeError, "motion_window must be an int >= 2"),
    (dict(predict="scene", prediction_weight="0.3"), TypeError, "prediction_weight must be a number in"),
    (dict(predict="scene", motion_window=1), ValueError, "motion_window must be an int >= 2"),
    (dict(predict="scene", prediction_weight=1.0), ValueError, "prediction_weight must be a number in \\[0, 1\\)"),
    (dict(predict="scene", max_correction_deg=0), ValueError, r"max_correction_deg must be in \(0, 180\] degrees"),
    (dict(iterations=0), ValueError, "iterations must be an integer from 1 to"),
    (dict(views=99), ValueError, "views must be an integer from 1 to"),
    (dict(lost_deg=0), ValueError, r"lost_deg must be in \(0, 180\] degrees"),
    (dict(lost_deg=float("nan")), ValueError, r"lost_deg must be in \(0, 180\] degrees"),
    (dict(lost_deg="2"), TypeError, "lost_deg must be a number of degrees"),
    (dict(lost_deg=True), TypeError, "lost_deg must be a number of degrees"),
    (dict(detector_weight=0), ValueError, r"detector_weight must be in \(0, 1\]"),
    (dict(detector_weight=1.5), ValueError, r"detector_weight must be in \(0, 1\]"),
    (dict(detector_weight=float("nan")), ValueError, r"detector_weight must be in \(0, 1\]"),
    (dict(detector_weight="0.3"), TypeError, r"detector_weight must be a number in \(0, 1\] or None"),
    (dict(detector_weight=True), TypeError, r"detector_weight must be a number in \(0, 1\] or None"),
    (dict(detector_weight=0.3, lost_deg=2.0), ValueError, "lost_deg and detector_weight are two uses"),
    (dict(reinit=True), ValueError, "reinit=True needs lost_deg"),
    (dict(reinit=1, lost_deg=2.5), TypeError, "reinit must be True or False"),
])
def test_bad_construction_is_named(kwargs, error, match):
    args = dict(session=session(), K=K, q0={"003_cracker_box": Q0[0]})
    args.update(kwargs)
    with pytest.raises(error, match=match):
        RefinerTracker(args.pop("session"), args.pop("K"), args.pop("q0"), **args)


def test_an_object_without_a_session_is_named():
    tracker = RefinerTracker({"003_cracker_box": session()}, K, {})
    with pytest.raises(ValueError, match=r"no session for object_id '011_banana'.*pass session="):
        tracker.add("011_banana", Q0[0])
    tracker.add("011_banana", Q0[0], session=session(objects=("011_banana",)))
    with pytest.raises(ValueError, match="'011_banana' is already tracked; use reset"):
        tracker.add("011_banana", Q0[0])
    with pytest.raises(ValueError, match=r"object_id names '004_sugar_box', which is not tracked"):
        tracker.reset("004_sugar_box", Q0[0])
    with pytest.raises(ValueError, match=r"object_id names '004_sugar_box', which is not tracked"):
        tracker.drop("004_sugar_box")


@pytest.mark.parametrize("image, boxes, error, match", [
    (IMG[..., 0], {"003_cracker_box": BOX_A}, ValueError, r"image must have shape \(H, W, 3\)"),
    (IMG.astype(np.float32), {"003_cracker_box": BOX_A}, ValueError, "image must have dtype uint8"),
    (IMG, [BOX_A], TypeError, r"boxes must be a mapping \{object id: \(4,\) box"),
    (IMG, {"003_cracker_box": [1, 2, 3]}, ValueError, r"boxes\['003_cracker_box'\] must be one box .* got shape \(3,\)"),
    (IMG, {"003_cracker_box": ["a", 2, 3, 4]}, ValueError, r"boxes\['003_cracker_box'\] must be one numeric box"),
    (IMG, {"003_cracker_box": [10, 10, 5, 20]}, ValueError, r"boxes\['003_cracker_box'\]"),
    (IMG, {"003_cracker_box": [100, 100, 120, 120]}, ValueError, r"boxes\['003_cracker_box'\]"),
    (IMG, {"003_cracker_box": [0, np.inf, 5, 20]}, ValueError, r"boxes\['003_cracker_box'\].*finite"),
    (IMG, {"011_banana": BOX_A}, ValueError, r"boxes names '011_banana', which is not tracked"),
])
def test_bad_updates_are_named_and_change_nothing(image, boxes, error, match):
    tracker = RefinerTracker(session(), K, {"003_cracker_box": Q0[0]})
    before = tracker.rotations
    with pytest.raises(error, match=match):
        tracker.update(image, boxes)
    np.testing.assert_array_equal(tracker.rotations["003_cracker_box"], before["003_cracker_box"])


# ------------------------------------------------------------------------------ the loss-of-track check
@pytest.mark.parametrize("frame", ["camera", "ray"])
def test_the_lost_check_flags_an_object_that_a_second_refinement_moves_too_far(frame):
    """The constant model moves every rotation by 7 degrees: above lost_deg=5 every checked update flags the
    object (not the first, refined from a coarse pose); with lost_deg=10 none does; either way the returned
    rotation is still q0 * c^n (no detector given)."""
    for lost_deg, flagged in ((5.0, True), (10.0, False)):
        tracker = _unfiltered(session(frame=frame), K, {"003_cracker_box": Q0[0]}, lost_deg=lost_deg)
        for n in range(1, 4):
            q = tracker.update(IMG, {"003_cracker_box": BOX_A})["003_cracker_box"]
            assert_same_rotation(q, scipy_q(Q0[0]) * scipy_q(Q_OUT) ** n)
            assert tracker.lost == (["003_cracker_box"] if flagged and n > 1 else [])
        assert tracker.redetections == 0


def test_a_lost_object_restarts_from_the_detector_pose_in_the_same_update():
    """With a detector, a flagged object is refined from the detector's pose instead: q = q_det * c (SciPy), its
    motion forgotten; the detector is asked for flagged objects only, and a mapping works as a callable does."""
    q_det = rq.from_axis_angle([1.0, 0.0, 0.0], 40.0)
    asked = []

    def detector(object_id):
        asked.append(object_id)
        return q_det

    shared = session(objects=("003_cracker_box", "011_banana"))
    tracker = RefinerTracker(shared, K, {"003_cracker_box": Q0[0], "011_banana": Q0[1]}, lost_deg=5.0, predict=True)
    boxes = {"003_cracker_box": BOX_A, "011_banana": BOX_B}
    tracker.update(IMG, boxes, detector=detector)  # from the coarse poses: not checked
    assert asked == [] and tracker.lost == []
    out = tracker.update(IMG, boxes, detector=detector)
    assert sorted(asked) == ["003_cracker_box", "011_banana"] and tracker.lost == [] and tracker.redetections == 2
    for object_id in boxes:
        assert_same_rotation(out[object_id], scipy_q(q_det) * scipy_q(Q_OUT))
        assert tracker._tracks[object_id].velocity is None
    out = tracker.update(IMG, {"011_banana": BOX_B}, detector={"003_cracker_box": q_det})  # no pose for the banana
    assert tracker.lost == ["011_banana"] and tracker.redetections == 2
    assert_same_rotation(out["011_banana"], scipy_q(q_det) * scipy_q(Q_OUT) ** 2)


def test_no_check_and_no_detector_call_without_lost_deg():
    tracker = RefinerTracker(session(), K, {"003_cracker_box": Q0[0]})
    for _ in range(3):
        tracker.update(IMG, {"003_cracker_box": BOX_A}, detector=lambda object_id: pytest.fail("asked"))
    assert tracker.lost == [] and tracker.redetections == 0


# ------------------------------------------------------------------------------ re-initialising from the box
class PullToTruth:
    """A made-up refiner (the :class:`refiner_rt.Refiner` protocol) with a known answer: each pass takes a rotation
    within ``basin_deg`` of ``truth`` onto it, and turns any other by ``walk_deg`` about the object's x axis (a view
    with no fixed point nearby). Rotations in the camera frame; boxes, K and the image are ignored."""

    per_call_passes = True

    def __init__(self, truth, basin_deg=75.0, walk_deg=10.0):
        from types import SimpleNamespace

        self.contract = SimpleNamespace(objects=("900_test_object",))
        self.truth = np.asarray(truth, dtype=np.float64)
        self.basin_deg, self.walk = basin_deg, rq.from_axis_angle([1.0, 0.0, 0.0], walk_deg)
        self.calls = []  # rows per call

    def _pass(self, q):
        near = rq.geodesic_angle(q, self.truth[None]) <= self.basin_deg
        return rq.canonical(np.where(near[:, None], self.truth[None], rq.multiply(q, np.tile(self.walk, (len(q), 1)))))

    def refine(self, image, boxes, q_in, *, K=None, D=None, coarse=None, iterations=1, views=1, settle_deg=None,
               q_order="wxyz"):
        q = rq.normalize(np.asarray(q_in, dtype=np.float64).reshape(-1, 4))
        self.calls.append(len(q))
        before = q
        for _ in range(iterations):
            before, q = q, self._pass(q)
        return RefineResult(q_refined=q, q_out=rq.canonical(rq.multiply(rq.inverse(before), q)), q_in=q_in)


TRUTH = rq.from_axis_angle([0.3, 0.5, -0.8], 40.0)
OBJ = "900_test_object"


def test_reinit_recovers_the_known_pose_of_a_track_that_walks_off():
    """A track 150 degrees off, where the refiner walks 40 degrees a pass: the check flags it at its second update
    (no detector), its own rotation refined 3 more times turns far (above the 15-degree gate), and the search over
    SO(3) finds the truth (one of its 8 starts lies within the refiner's basin; the truth comes back from a 15-degree
    turn, while the walking track lands at least 40 - 15 degrees away, more than the 20-degree margin it is given);
    one more pass leaves the truth where it is, so it is taken: the update returns the truth, the track is
    re-initialised (not lost) and stays there."""
    start = rq.multiply(TRUTH, rq.from_axis_angle([1.0, 0.0, 0.0], 150.0))
    refiner = PullToTruth(TRUTH, walk_deg=40.0)
    tracker = RefinerTracker({OBJ: refiner}, K, {OBJ: start}, lost_deg=2.5, reinit=True)
    tracker.update(IMG, {OBJ: BOX_A})  # from the coarse pose: not checked
    assert tracker.lost == [] and tracker.reinits == 0
    q = tracker.update(IMG, {OBJ: BOX_A})[OBJ]
    assert tracker.reinits == 1 and tracker.lost == [] and tracker.redetections == 0
    assert tracker.reinitialised == [OBJ]  # this update's
    assert rq.geodesic_angle(q, TRUTH) < 1e-6
    for _ in range(2):  # a new start at the truth: nothing flagged, nothing searched
        calls = len(refiner.calls)
        q = tracker.update(IMG, {OBJ: BOX_A})[OBJ]
        assert rq.geodesic_angle(q, TRUTH) < 1e-6
        assert tracker.lost == [] and tracker.reinits == 1 and len(refiner.calls) == calls + 2  # update and check
        assert tracker.reinitialised == []


def test_reinit_searches_many_flagged_tracks_in_calls_within_the_batch_limit():
    """200 instances of one object, each 150 degrees off: all are flagged at once and the search (9 starts each, 1,800
    rows) runs in chunks whose every call stays within MAX_BATCH crops; every track gets the truth back."""
    from refiner_rt.checks import MAX_BATCH

    start = rq.multiply(TRUTH, rq.from_axis_angle([1.0, 0.0, 0.0], 150.0))
    refiner = PullToTruth(TRUTH, walk_deg=40.0)
    ids = [f"{OBJ}#{k}" for k in range(200)]
    tracker = RefinerTracker(refiner, K, {i: start for i in ids}, lost_deg=2.5, reinit=True)
    boxes = {i: BOX_A for i in ids}
    tracker.update(IMG, boxes)
    out = tracker.update(IMG, boxes)
    assert tracker.reinits == 200 and tracker.lost == [] and sorted(tracker.reinitialised) == sorted(ids)
    assert max(rq.geodesic_angle(np.array([out[i] for i in ids]), TRUTH[None])) < 1e-6
    assert max(refiner.calls) <= MAX_BATCH and sum(c > 200 for c in refiner.calls) >= 2  # the search's calls, chunked


class PullToTruthPerPass(PullToTruth):
    """:class:`PullToTruth` as a cascade calls it: one pass per call (``per_call_passes`` False), views of its own."""

    per_call_passes = False
    coarse_views, fine_views = 2, 2

    def refine(self, image, boxes, q_in, *, K=None, D=None, coarse=None, q_order="wxyz"):
        return super().refine(image, boxes, q_in, K=K, D=D, coarse=coarse)


@pytest.mark.parametrize("distorted", [False, True])
def test_reinit_with_a_cascade_and_a_distorted_camera(distorted):
    """The re-initialisation through a refiner that takes one pass per call (a cascade: the passes are calls) and with
    lens distortion (the search's boxes undistorted first): the walked-off track gets the truth back, as with a
    session; the hypotheses' passes came as single-pass calls of 8 rows."""
    start = rq.multiply(TRUTH, rq.from_axis_angle([1.0, 0.0, 0.0], 150.0))
    refiner = PullToTruthPerPass(TRUTH, walk_deg=40.0)
    D = [0.1, -0.05, 0.001, 0.0005, 0.0] if distorted else None
    tracker = RefinerTracker({OBJ: refiner}, K, {OBJ: start}, lost_deg=2.5, reinit=True, D=D)
    tracker.update(IMG, {OBJ: BOX_A})
    q = tracker.update(IMG, {OBJ: BOX_A})[OBJ]
    assert tracker.reinits == 1 and tracker.reinitialised == [OBJ] and tracker.lost == []
    assert rq.geodesic_angle(q, TRUTH) < 1e-6
    assert refiner.calls.count(8) == 3  # REINIT_PASSES single-pass calls of the 8 hypotheses


def test_reinit_costs_nothing_on_a_good_track():
    """A track at the truth is never flagged: the same rotations as without reinit, two refine calls per update
    (the update and the check), no search."""
    near = rq.multiply(TRUTH, rq.from_axis_angle([0.0, 1.0, 0.0], 10.0))
    plain, searched = PullToTruth(TRUTH), PullToTruth(TRUTH)
    a = RefinerTracker({OBJ: plain}, K, {OBJ: near}, lost_deg=2.5)
    b = RefinerTracker({OBJ: searched}, K, {OBJ: near}, lost_deg=2.5, reinit=True)
    for _ in range(4):
        np.testing.assert_array_equal(a.update(IMG, {OBJ: BOX_A})[OBJ], b.update(IMG, {OBJ: BOX_A})[OBJ])
        assert b.lost == [] and b.reinits == 0
    assert plain.calls == searched.calls == [1] + [1, 1] * 3


def test_reinit_keeps_a_flagged_track_its_own_passes_barely_move():
    """A track the refiner walks 4 degrees a pass is flagged (4 > 2.5) but its own 3 passes turn it 12 degrees, under
    the 15-degree gate: no search, the track kept as the filter has it, and listed lost."""
    start = rq.multiply(TRUTH, rq.from_axis_angle([1.0, 0.0, 0.0], 150.0))
    plain, searched = PullToTruth(TRUTH, walk_deg=4.0), PullToTruth(TRUTH, walk_deg=4.0)
    a = RefinerTracker({OBJ: plain}, K, {OBJ: start}, lost_deg=2.5)
    b = RefinerTracker({OBJ: searched}, K, {OBJ: start}, lost_deg=2.5, reinit=True)
    for n in range(3):
        np.testing.assert_array_equal(a.update(IMG, {OBJ: BOX_A})[OBJ], b.update(IMG, {OBJ: BOX_A})[OBJ])
        assert b.lost == ([OBJ] if n else []) and b.reinits == 0
    assert searched.calls == [1] + [1, 1, 1] * 2  # update, check, and the own rotation's passes (one call)


def test_reinit_takes_no_start_the_check_would_flag_again():
    """The constant model turns every rotation by 7 degrees, at the truth too: the gate opens (21 degrees in 3
    passes), but every start the search ranks first moves 7 degrees more, above lost_deg: nothing is taken, the
    rotation is q0 * c^n as without reinit, and the object is listed lost."""
    tracker = _unfiltered(session(frame="ray"), K, {"003_cracker_box": Q0[0]}, lost_deg=5.0, reinit=True)
    for n in range(1, 4):
        q = tracker.update(IMG, {"003_cracker_box": BOX_A})["003_cracker_box"]
        assert_same_rotation(q, scipy_q(Q0[0]) * scipy_q(Q_OUT) ** n)
        assert tracker.lost == (["003_cracker_box"] if n > 1 else []) and tracker.reinits == 0


def test_a_detector_pose_comes_before_the_search():
    """With a detector pose for a flagged object the tracker restarts from it (a redetection), no search."""
    start = rq.multiply(TRUTH, rq.from_axis_angle([1.0, 0.0, 0.0], 150.0))
    refiner = PullToTruth(TRUTH, walk_deg=40.0)
    tracker = RefinerTracker({OBJ: refiner}, K, {OBJ: start}, lost_deg=2.5, reinit=True)
    tracker.update(IMG, {OBJ: BOX_A})
    q_det = rq.multiply(TRUTH, rq.from_axis_angle([0.0, 0.0, 1.0], 20.0))
    q = tracker.update(IMG, {OBJ: BOX_A}, detector={OBJ: q_det})[OBJ]
    assert tracker.redetections == 1 and tracker.reinits == 0 and rq.geodesic_angle(q, TRUTH) < 1e-6
    assert refiner.calls == [1, 1, 1, 1]  # update, check, the detection's refinement


# ------------------------------------------------------------------------------ fusing a detector
@pytest.mark.parametrize("frame", ["camera", "ray"])
@pytest.mark.parametrize("w", [0.3, 1.0])
def test_a_fused_detection_moves_the_track_w_of_the_way(frame, w):
    """Refined track q_t * c and refined detection q_det * c (the constant model's c), fused: SciPy's Slerp at w
    between them; w = 1 is the refined detection (per-frame refinement); an update without a pose is plain tracking."""
    from scipy.spatial.transform import Slerp

    q_det = rq.from_axis_angle([1.0, 0.2, 0.0], 25.0)
    tracker = _unfiltered(session(frame=frame), K, {"003_cracker_box": Q0[0]}, detector_weight=w)
    q = tracker.update(IMG, {"003_cracker_box": BOX_A}, detector={"003_cracker_box": q_det})["003_cracker_box"]
    ends = Rotation.concatenate([scipy_q(Q0[0]) * scipy_q(Q_OUT), scipy_q(q_det) * scipy_q(Q_OUT)])
    want = Slerp([0.0, 1.0], ends)([w])[0]
    assert_same_rotation(q, want)
    assert q[0] >= 0
    q2 = tracker.update(IMG, {"003_cracker_box": BOX_A}, detector=lambda object_id: None)["003_cracker_box"]
    assert_same_rotation(q2, want * scipy_q(Q_OUT))


def test_update_from_detector_starts_fuses_or_restarts_from_each_pose():
    """The per-frame step both `refiner-rt track` paths run: a pose starts an untracked object; for a tracked one it
    is fused with detector_weight, else it restarts the track; a pose without a box, or a box of an object neither
    tracked nor posed, is refused by name."""
    from scipy.spatial.transform import Slerp

    q_det = rq.from_axis_angle([1.0, 0.2, 0.0], 25.0)
    c = scipy_q(Q_OUT)
    for w in (None, 0.5):
        tracker = _unfiltered({}, K, {}, detector_weight=w)
        first = tracker.update_from_detector(IMG, {"003_cracker_box": BOX_A}, {"003_cracker_box": Q0[0]},
                                             sessions={"003_cracker_box": session()})
        assert_same_rotation(first["003_cracker_box"], scipy_q(Q0[0]) * c)
        q = tracker.update_from_detector(IMG, {"003_cracker_box": BOX_A}, {"003_cracker_box": q_det})
        track, det = scipy_q(Q0[0]) * c * c, scipy_q(q_det) * c
        want = det if w is None else Slerp([0.0, 1.0], Rotation.concatenate([track, det]))([w])[0]
        assert_same_rotation(q["003_cracker_box"], want)
        q = tracker.update_from_detector(IMG, {"003_cracker_box": BOX_A}, {})  # box only: plain tracking
        assert_same_rotation(q["003_cracker_box"], want * c)
    with pytest.raises(ValueError, match=r"poses names \['011_banana'\], which have no box"):
        tracker.update_from_detector(IMG, {"003_cracker_box": BOX_A}, {"011_banana": Q0[1]})
    with pytest.raises(ValueError, match="boxes names '011_banana', which is not tracked"):
        tracker.update_from_detector(IMG, {"011_banana": BOX_B}, {})


def test_fusing_refines_tracks_and_detections_in_one_call(monkeypatch):
    shared = session(objects=("003_cracker_box", "011_banana"))
    calls = []
    real = shared.refine

    def spy(image, boxes, q_in, **kw):
        calls.append((np.asarray(boxes).copy(), np.asarray(q_in).copy()))
        return real(image, boxes, q_in, **kw)

    monkeypatch.setattr(shared, "refine", spy)
    tracker = RefinerTracker(shared, K, {"003_cracker_box": Q0[0], "011_banana": Q0[1]}, detector_weight=0.5)
    q_det = rq.from_axis_angle([0.0, 1.0, 0.0], 10.0)
    tracker.update(IMG, {"003_cracker_box": BOX_A, "011_banana": BOX_B}, detector={"011_banana": q_det})
    assert len(calls) == 1
    boxes, q_in = calls[0]
    np.testing.assert_allclose(boxes, [BOX_A, BOX_B, BOX_B])  # the banana twice: its track and its detection
    np.testing.assert_allclose(q_in, np.stack([Q0[0], Q0[1], q_det]), atol=1e-12)
    # ... and each result is its own: the cracker box plainly tracked, the banana fused with its detection.
    from scipy.spatial.transform import Slerp

    out = tracker.rotations
    assert_same_rotation(out["003_cracker_box"], scipy_q(Q0[0]) * scipy_q(Q_OUT))
    ends = Rotation.concatenate([scipy_q(Q0[1]) * scipy_q(Q_OUT), scipy_q(q_det) * scipy_q(Q_OUT)])
    assert_same_rotation(out["011_banana"], Slerp([0.0, 1.0], ends)([0.5])[0])


def test_a_fused_detection_far_from_the_track_takes_the_shortest_arc():
    """A detection 150 degrees from the track: the fused rotation lies on the shorter arc (75 degrees from each)."""
    q_det = rq.multiply(Q0[0], rq.from_axis_angle([0.0, 1.0, 0.0], 150.0))
    tracker = RefinerTracker(session(q_out=rq.identity()), K, {"003_cracker_box": Q0[0]}, detector_weight=0.5)
    q = tracker.update(IMG, {"003_cracker_box": BOX_A}, detector={"003_cracker_box": q_det})["003_cracker_box"]
    assert rq.geodesic_angle(q, Q0[0]) == pytest.approx(75.0, abs=1e-6)
    assert rq.geodesic_angle(q, q_det) == pytest.approx(75.0, abs=1e-6)


def test_fused_detections_do_not_become_velocity():
    """With predict=True the velocity comes from the refined track, not from the detector's pull: a model that never
    corrects and a fused detection far away leave a still object's velocity the identity."""
    tracker = RefinerTracker(session(q_out=rq.identity()), K, {"003_cracker_box": Q0[0]}, detector_weight=0.5,
                             predict=True)
    tracker.update(IMG, {"003_cracker_box": BOX_A})
    tracker.update(IMG, {"003_cracker_box": BOX_A}, detector={"003_cracker_box": rq.from_axis_angle([1, 0, 0], 20.0)})
    velocity = tracker._tracks["003_cracker_box"].velocity
    assert rq.geodesic_angle(velocity, rq.identity()) == pytest.approx(0.0, abs=1e-6)


@pytest.mark.parametrize("detector, error, match", [
    (3, TypeError, "detector must be a callable detector"),
    ({"003_cracker_box": [0, 0, 0, 0]}, ValueError, r"detector pose for '003_cracker_box' must be non-zero"),
    (lambda object_id: [1, 0, 0], ValueError, r"detector pose for '003_cracker_box' must have shape"),
])
def test_a_bad_detector_is_named_and_changes_nothing(detector, error, match):
    tracker = RefinerTracker(session(), K, {"003_cracker_box": Q0[0]}, lost_deg=5.0)
    tracker.update(IMG, {"003_cracker_box": BOX_A})
    before = tracker.rotations["003_cracker_box"]
    with pytest.raises(error, match=match):
        tracker.update(IMG, {"003_cracker_box": BOX_A}, detector=detector)
    np.testing.assert_array_equal(tracker.rotations["003_cracker_box"], before)


# ------------------------------------------------------------------------------ refiner-rt track
def write_sequence(folder, n=3, q0=Q0[0], extra=None):
    """``n`` PNG frames, a constant-correction model for the cracker box and a detections file (first frame with q0)."""
    import json

    import cv2

    frames = folder / "frames"
    frames.mkdir()
    for i in range(n):
        cv2.imwrite(str(frames / f"{i:06d}.png"), np.roll(IMG, 2 * i, axis=1))
    model = folder / "box.onnx"
    model.write_bytes(fx.constant_model(Q_OUT, props=fx.contract(objects=["003_cracker_box"], rotation_frame="ray")))
    doc = {"K": K.tolist(), "frames": {f"{i:06d}.png": {"003_cracker_box": list(BOX_A)} for i in range(n)}}
    doc["frames"]["000000.png"]["003_cracker_box"] = {"box": BOX_A, "q": list(q0)}
    doc.update(extra or {})
    (folder / "detections.json").write_text(json.dumps(doc))
    return frames, folder / "detections.json", model


def test_track_command_writes_each_frames_score_and_the_lost_flag(tmp_path):
    """The frames path's JSON: per frame each object's RefineResult.score (a constant 7-degree correction scores
    exp(-7 / SCORE_SCALE_DEG)) and, with --lost-deg, the objects flagged lost: the second pass moves the track by 7
    degrees, so from the second frame on (the first is refined from the coarse pose, not checked) it is lost."""
    import json

    from click.testing import CliRunner

    from refiner_rt.cli import main
    from refiner_rt.session import SCORE_SCALE_DEG

    frames, dets, model = write_sequence(tmp_path, n=4)
    out = tmp_path / "rot.json"
    res = CliRunner().invoke(main, ["track", str(frames), str(dets), "-o", str(out), "--model", str(model),
                                    "--lost-deg", "5"])
    assert res.exit_code == 0, res.output
    doc = json.loads(out.read_text())
    assert list(doc["scores"]) == [f"{i:06d}.png" for i in range(4)]
    for name, scores in doc["scores"].items():
        assert scores["003_cracker_box"] == pytest.approx(np.exp(-7.0 / SCORE_SCALE_DEG), abs=1e-4)
    assert doc["lost"] == {f"{i:06d}.png": ["003_cracker_box"] for i in range(1, 4)}
    res = CliRunner().invoke(main, ["track", str(frames), str(dets), "-o", str(out), "--model", str(model),
                                    "--lost-deg", "8"])
    assert json.loads(out.read_text())["lost"] == {}


def test_track_command_writes_the_tracked_rotations_and_a_strip(tmp_path):
    import json

    import cv2
    from click.testing import CliRunner

    from refiner_rt.cli import main

    frames, dets, model = write_sequence(tmp_path, n=4)
    out, strip = tmp_path / "out" / "rot.json", tmp_path / "pictures" / "strip.png"  # missing folders are made
    res = CliRunner().invoke(main, ["track", str(frames), str(dets), "-o", str(out), "--model", str(model),
                                    "--video", str(strip), "--strip", "3"])
    assert res.exit_code == 0, res.output
    assert "4 frames, 1 objects, 4 refinements" in res.output
    doc = json.loads(out.read_text())
    assert doc["format"] == "refiner-rt/track/1" and list(doc["frames"]) == [f"{i:06d}.png" for i in range(4)]
    for i, name in enumerate(doc["frames"]):
        assert_same_rotation(np.array(doc["frames"][name]["003_cracker_box"]),
                             scipy_q(Q0[0]) * scipy_q(Q_OUT) ** (1 + HELD * i))  # the default filter: 3 of 7 degrees
    image = cv2.imread(str(strip))
    assert image.shape == (240, 3 * 320, 3)
    res = CliRunner().invoke(main, ["track", str(frames), str(dets), "-o", str(out), "--model", str(model),
                                    "--video", str(tmp_path / "v.avi"), "--predict"])
    assert res.exit_code == 0, res.output
    assert (tmp_path / "v.avi").stat().st_size > 0
    assert json.loads(out.read_text())["lost"] == {}


def test_track_command_scene_motion(tmp_path):
    """--scene-motion is RefinerTracker(predict="scene") with its defaults (window 4, prediction weight 0.3), recorded
    in the output; with --predict it is a usage error that names both."""
    import json

    from click.testing import CliRunner

    from refiner_rt.cli import main

    frames, dets, model = write_sequence(tmp_path, n=6)
    out = tmp_path / "rot.json"
    res = CliRunner().invoke(main, ["track", str(frames), str(dets), "-o", str(out), "--model", str(model),
                                    "--scene-motion"])
    assert res.exit_code == 0, res.output
    doc = json.loads(out.read_text())
    assert doc["scene_motion"] is True and doc["predict"] is False
    ref = scene_reference({"003_cracker_box": scipy_q(Q0[0])}, scipy_q(Q_OUT), [{"003_cracker_box"}] * 6, 4, 0.3)
    assert_same_rotation(np.array(doc["frames"]["000005.png"]["003_cracker_box"]), ref["003_cracker_box"])
    res = CliRunner().invoke(main, ["track", str(frames), str(dets), "-o", str(out), "--model", str(model),
                                    "--scene-motion", "--predict"])
    assert res.exit_code == 2 and "--predict" in res.output and "--scene-motion" in res.output
    assert "Traceback" not in res.output


@pytest.mark.parametrize("option, n, refused", [
    ("views", 4, [["--views", "4", "--cascade"]]),
    ("starts", 5, [["--starts", "5", "--cascade"], ["--starts", "3"]]),
])
def test_track_command_views_and_starts_average_per_update(tmp_path, option, n, refused):
    """--views N and --starts N are RefinerTracker(views=N) / (starts=N): each update averages N box-jittered crops,
    or N turned starts each on its own jitter (a crop- and rotation-dependent model, so N differ from one); recorded
    in the output; with --cascade, and out of range, a usage error naming the option."""
    import json

    import cv2
    from click.testing import CliRunner

    from refiner_rt.cli import main

    frames, dets, model = write_sequence(tmp_path, n=3)
    model.write_bytes(fx.random_weight_model(seed=5, props=fx.contract(objects=["003_cracker_box"],
                                                                       rotation_frame="ray")))
    out = tmp_path / "rot.json"
    got = {}
    for value in (1, n):
        res = CliRunner().invoke(main, ["track", str(frames), str(dets), "-o", str(out), "--model", str(model),
                                        f"--{option}", str(value)])
        assert res.exit_code == 0, res.output
        doc = json.loads(out.read_text())
        assert doc[option] == value
        tracker = RefinerTracker(RefinerSession(str(model)), K, {"003_cracker_box": Q0[0]}, **{option: value})
        for name in sorted(doc["frames"]):
            want = tracker.update(cv2.imread(str(frames / name)), {"003_cracker_box": BOX_A})["003_cracker_box"]
            assert_same_rotation(np.array(doc["frames"][name]["003_cracker_box"]), scipy_q(want))
        got[value] = np.array(doc["frames"]["000002.png"]["003_cracker_box"])
    assert rq.geodesic_angle(got[1], got[n]) > 1e-3  # the option reached the network
    for args in refused:
        res = CliRunner().invoke(main, ["track", str(frames), str(dets), "-o", str(out), *args])
        assert res.exit_code == 2 and f"--{option}" in res.output and "Traceback" not in res.output, res.output
        assert "--cascade" not in args or "--cascade" in res.output


def test_track_command_fuses_later_detector_poses_with_detector_weight(tmp_path):
    """A "q" on the third frame: without --detector-weight it restarts the track (q_det * c); with 0.5 it is refined
    beside the track and the rotation is half way between the two (SciPy's Slerp)."""
    import json

    from click.testing import CliRunner
    from scipy.spatial.transform import Slerp

    from refiner_rt.cli import main

    q_det = rq.from_axis_angle([0.0, 0.0, 1.0], 20.0)
    frames, dets, model = write_sequence(tmp_path, n=3)
    doc = json.loads(dets.read_text())
    doc["frames"]["000002.png"]["003_cracker_box"] = {"box": BOX_A, "q": list(q_det)}
    dets.write_text(json.dumps(doc))
    track = scipy_q(Q0[0]) * scipy_q(Q_OUT) ** (1 + 2 * HELD)  # the track's own update held to 3 degrees
    det = scipy_q(q_det) * scipy_q(Q_OUT)
    for extra, want in (([], det), (["--detector-weight", "0.5"], Slerp([0, 1], Rotation.concatenate([track, det]))([0.5])[0])):
        out = tmp_path / "rot.json"
        res = CliRunner().invoke(main, ["track", str(frames), str(dets), "-o", str(out), "--model", str(model), *extra])
        assert res.exit_code == 0, res.output
        assert_same_rotation(np.array(json.loads(out.read_text())["frames"]["000002.png"]["003_cracker_box"]), want)
    for bad in (["--detector-weight", "0"], ["--detector-weight", "0.5", "--lost-deg", "2"]):
        res = CliRunner().invoke(main, ["track", str(frames), str(dets), "-o", str(out), "--model", str(model), *bad])
        assert res.exit_code == 2 and "--detector-weight" in res.output and "Traceback" not in res.output


@pytest.mark.parametrize("lost_deg, lost_frames", [("5", ["000001.png", "000002.png"]), ("10", [])])
def test_track_command_lists_the_frames_where_the_lost_check_fires(tmp_path, lost_deg, lost_frames):
    """The constant model moves every rotation by 7 degrees: a check at 5 fires on every frame after the first."""
    import json

    from click.testing import CliRunner

    from refiner_rt.cli import main

    frames, dets, model = write_sequence(tmp_path, n=3)
    out = tmp_path / "rot.json"
    res = CliRunner().invoke(main, ["track", str(frames), str(dets), "-o", str(out), "--model", str(model),
                                    "--lost-deg", lost_deg])
    assert res.exit_code == 0, res.output
    doc = json.loads(out.read_text())
    assert doc["lost_deg"] == float(lost_deg)
    assert doc["lost"] == {name: ["003_cracker_box"] for name in lost_frames}
    res = CliRunner().invoke(main, ["track", str(frames), str(dets), "-o", str(out), "--model", str(model),
                                    "--lost-deg", "0"])
    assert res.exit_code != 0 and "--lost-deg" in res.output


def test_track_command_reinit_searches_flagged_tracks_and_needs_lost_deg(tmp_path):
    """--reinit with --lost-deg: the tracker gets reinit=True (the constant model's starts all move 7 degrees more, so
    nothing is taken and the frames stay lost, as test_reinit_takes_no_start_the_check_would_flag_again shows for the
    class); the output records it; without --lost-deg the command refuses it, naming both flags."""
    import json

    from click.testing import CliRunner

    from refiner_rt.cli import main

    frames, dets, model = write_sequence(tmp_path, n=3)
    out = tmp_path / "rot.json"
    res = CliRunner().invoke(main, ["track", str(frames), str(dets), "-o", str(out), "--model", str(model),
                                    "--lost-deg", "5", "--reinit"])
    assert res.exit_code == 0, res.output
    doc = json.loads(out.read_text())
    assert doc["reinit"] is True and doc["reinits"] == 0 and doc["reinitialised"] == {}
    assert doc["lost"] == {name: ["003_cracker_box"] for name in ("000001.png", "000002.png")}
    res = CliRunner().invoke(main, ["track", str(frames), str(dets), "-o", str(out), "--model", str(model),
                                    "--reinit"])
    assert res.exit_code == 2 and "--reinit" in res.output and "--lost-deg" in res.output


def test_track_command_with_shipped_names_and_a_reset(tmp_path, weights):  # noqa: F811
    import json

    from click.testing import CliRunner

    from refiner_rt.cli import main

    frames, dets, _ = write_sequence(tmp_path, n=3)
    doc = json.loads(dets.read_text())
    doc["frames"]["000002.png"]["003_cracker_box"] = {"box": BOX_A, "q": [0, 1, 0, 0]}
    del doc["K"]
    dets.write_text(json.dumps(doc))
    out = tmp_path / "rot.json"
    res = CliRunner().invoke(main, ["track", str(frames), str(dets), "-o", str(out), "--K", "60,60,31.5,23.5"])
    assert res.exit_code == 0, res.output
    rot = json.loads(out.read_text())
    assert rot["models"]["003_cracker_box"].endswith("003_cracker_box.int8.onnx")
    # The made-up shipped model corrects by the identity: the rotation is q0 until the reset gives (0, 1, 0, 0).
    assert_same_rotation(np.array(rot["frames"]["000001.png"]["003_cracker_box"]), scipy_q(Q0[0]))
    np.testing.assert_allclose(rot["frames"]["000002.png"]["003_cracker_box"], [0, 1, 0, 0], atol=1e-9)


@pytest.mark.parametrize("change, args, match", [
    ({"K": None}, [], "no camera intrinsics"),
    ({}, ["--K", "1,2,3"], "expected four numbers FX,FY,CX,CY"),
    ({"frames": {"nope.png": {"003_cracker_box": BOX_A}}}, [], r"frames \['nope.png'\] are not images in"),
    ({"frames": {"000000.png": {"003_cracker_box": [1, 2]}}}, [], r"box \(x1, y1, x2, y2\) must have shape \(4,\)"),
    ({"frames": {"000000.png": {"003_cracker_box": {"box": BOX_A, "q": [0, 0, 0, 0]}}}}, [], "000000.png: q must be non-zero"),
    ({"frames": {"000000.png": {"003_cracker_box": {"box": [500, 500, 510, 510], "q": [1, 0, 0, 0]}}}}, [],
     r"000000.png: boxes\['003_cracker_box'\]"),
    ({"frames": {"000001.png": {"003_cracker_box": BOX_A}}}, [], "has a box but no rotation to start from"),
    ({"frames": {"000000.png": {"005_tomato_soup_can": {"box": BOX_A, "q": [1, 0, 0, 0]}}}}, [],
     "no pretrained model for object '005_tomato_soup_can'"),  # a YCB object that no model ships for
    ({}, ["--video", "x.gif"], "expected a .mp4 or .avi video or a .png or .jpg image strip"),
    ({}, ["-o", "out.mp4"], r"expected a .json file for the rotations \(a video or image strip goes to --video\)"),
])
def test_track_command_refuses_bad_input_without_a_traceback(tmp_path, change, args, match):
    import json

    from click.testing import CliRunner

    from refiner_rt.cli import main

    frames, dets, model = write_sequence(tmp_path)
    doc = json.loads(dets.read_text())
    doc.update(change)
    if doc["K"] is None:
        del doc["K"]
    dets.write_text(json.dumps(doc))
    res = CliRunner().invoke(main, ["track", str(frames), str(dets), "-o", str(tmp_path / "r.json"), "--model",
                                    str(model), *args])
    assert res.exit_code != 0 and "Traceback" not in res.output
    assert res.exception is None or isinstance(res.exception, SystemExit)
    assert __import__("re").search(match, res.output), res.output


def test_track_command_refuses_a_file_that_is_not_json_and_a_model_that_is_not_onnx(tmp_path):
    from click.testing import CliRunner

    from refiner_rt.cli import main

    frames, dets, model = write_sequence(tmp_path)
    model.write_bytes(b"not a model")
    res = CliRunner().invoke(main, ["track", str(frames), str(dets), "-o", str(tmp_path / "r.json"), "--model", str(model)])
    assert res.exit_code == 1 and "Traceback" not in res.output and "box.onnx" in res.output, res.output
    dets.write_text("{not json")
    res = CliRunner().invoke(main, ["track", str(frames), str(dets), "-o", str(tmp_path / "new" / "r.json")])
    assert res.exit_code == 1 and "not a readable JSON detections file" in res.output
    assert not (tmp_path / "new").exists()  # the output's folder is made once the inputs are read, not before


# ------------------------------------------------------------------------------ benchmarks/tracking.py
def test_tracking_benchmark_on_a_tiny_rendered_path(tmp_path):
    """Two short BOP scenes turning 2 degrees a frame and a model that never corrects: tracking then equals holding
    the initial pose, and per-frame refinement's error is the drawn coarse error (mean near 15 degrees)."""
    import json

    from tests.bench_scripts import load_benchmark
    from tests.data_fixtures import bop_instance, write_bop_scene

    bench = load_benchmark("tracking")
    data = tmp_path / "data"
    turn = rq.from_axis_angle([0.0, 0.0, 1.0], 2.0)
    for scene in (0, 1):
        q = Q0[scene]
        frames = {}
        for f in range(12):
            frames[f] = [bop_instance(2, rq.to_matrix(q), [0.0, 0.0, 800.0], [20 + f, 10, 30, 30],
                                      visib_fract=0.1 if (scene, f) == (1, 5) else 0.9)]
            q = rq.multiply(turn, q)
        write_bop_scene(data, scene, frames, K * 10 * np.array([[1, 1, 1], [1, 1, 1], [0, 0, 0.1]]), size=(96, 64),
                        seed=scene)
    model = tmp_path / "ident.onnx"
    model.write_bytes(fx.constant_model(rq.identity(), props=fx.contract(objects=["003_cracker_box"], rotation_frame="ray")))
    out, png = tmp_path / "tracking.json", tmp_path / "tracking.png"
    assert bench.main(["--data", str(data), "--model", f"003_cracker_box={model}", "--min-frames", "5", "--redetect", "4",
                       "--json", str(out), "--plot", str(png), "--detections-out", str(tmp_path / "dets")]) == 0
    doc = json.loads(out.read_text())
    s = doc["summary"]
    assert doc["sequences_per_object"] == {"003_cracker_box": 2} and doc["steps"] == [1, 2, 4]
    for step in ("1", "2", "4"):
        assert s["track"][step]["mean_deg"] == s["hold"][step]["mean_deg"]
        assert s["track_predict"][step]["mean_deg"] == s["hold"][step]["mean_deg"]
        # nor does the scene's motion: the refined rotations never change, so the estimated turn is none
        assert s["track_scene"][step]["mean_deg"] == pytest.approx(s["hold"][step]["mean_deg"], abs=1e-3)
        assert s["track_redetect"][step]["mean_deg"] < s["hold"][step]["mean_deg"]  # reset to fresh draws
        assert 5 < s["per_frame"][step]["mean_deg"] < 25
        # A model that never corrects agrees with itself: the loss check never fires, no detector is asked.
        assert s["track_lost"][step]["mean_deg"] == s["hold"][step]["mean_deg"]
        assert s["track_lost"][step]["detector_share"] == 0 and s["per_frame"][step]["detector_share"] == 1
        # Fusing the fresh draws pulls the held pose towards the truth.
        assert s["track_fuse"][step]["mean_deg"] < s["hold"][step]["mean_deg"]
    assert s["track_redetect"]["1"]["detector_share"] == round(4 / 23, 4)  # frames 4 and 8 of both, frame 5 unscored
    assert s["hold"]["1"]["frames"] == 23  # 2 x 12 frames, one below --min-visib
    assert s["track_fuse"]["1"]["detector_share"] == round(21 / 23, 4)  # every scored frame after each start
    # Holding the pose drifts by the 2-degree turn per frame: the curve rises over the sequence.
    curve = doc["curves"]["hold"]["1"]
    assert curve[11] > curve[0] + 10
    assert doc["cost"]["track_step1"]["refinements"] == 23 and doc["machine"]["cpu"]
    assert png.stat().st_size > 10_000
    table = bench.report(doc)
    assert len(table.splitlines()) == 2 + 3 * 8 and "| 1 | (c) track |" in table
    assert "| 1 | (c) track + the scene's motion (window 4, weight 0.3, at most 2.0 deg) |" in table
    # The detections it writes run through `refiner-rt track`: with this model the rotation stays the initial pose.
    from click.testing import CliRunner

    from refiner_rt.cli import main

    res = CliRunner().invoke(main, ["track", str(data / "000001" / "rgb"), str(tmp_path / "dets" / "000001.json"),
                                    "-o", str(tmp_path / "rot.json"), "--model", str(model)])
    assert res.exit_code == 0, res.output
    rot = json.loads((tmp_path / "rot.json").read_text())["frames"]
    assert len(rot) == 12 and rot["000005.png"] == {}  # frame 5 had no box
    truth0 = Q0[1]
    held = [rq.geodesic_angle(q["003_cracker_box"], truth0) for q in rot.values() if q]
    assert np.ptp(held) < 1e-6 and held[0] <= 30.0 + 1e-6


def test_tracking_benchmark_runs_the_shipped_cascade_with_settle_deg(tmp_path, capsys):
    """--settle-deg reaches the cascades of the cascade methods (their second coarse pass) and is recorded."""
    import json

    from tests.bench_scripts import load_benchmark
    from tests.data_fixtures import bop_instance, write_bop_scene
    from refiner_rt import pretrained_models

    if not any(m.object_id == "003_cracker_box" and "fine" in m.stages for m in pretrained_models()):
        pytest.skip("no cracker-box fine refiner ships in this checkout")
    bench = load_benchmark("tracking")
    data = tmp_path / "data"
    frames = {f: [bop_instance(2, rq.to_matrix(Q0[0]), [0.0, 0.0, 800.0], [20, 10, 40, 40], visib_fract=0.9)]
              for f in range(6)}
    write_bop_scene(data, 0, frames, K * 10 * np.array([[1, 1, 1], [1, 1, 1], [0, 0, 0.1]]), size=(96, 64), seed=0)
    runs = {}
    for settle in (None, 2.0):
        out = tmp_path / f"tracking_{settle}.json"
        args = ["--data", str(data), "--objects", "003_cracker_box", "--methods", "hold,per_frame_cascade,track_cascade",
                "--steps", "1", "--min-frames", "5", "--json", str(out)]
        assert bench.main(args + (["--settle-deg", str(settle)] if settle else [])) == 0
        runs[settle] = json.loads(out.read_text())
    assert runs[None]["settle_deg"] is None and runs[2.0]["settle_deg"] == 2.0
    for doc in runs.values():
        assert np.isfinite(doc["summary"]["track_cascade"]["1"]["mean_deg"])
    # The held pose does not depend on the cascade's settings.
    assert runs[None]["summary"]["hold"] == runs[2.0]["summary"]["hold"]
    # A bad value, or one no method uses, is refused with the option's name.
    base = ["--data", str(data), "--objects", "003_cracker_box", "--steps", "1", "--min-frames", "5"]
    for extra, words in ((["--methods", "hold,track", "--motion-window", "6"], "apply to the _scene methods"),
                         (["--methods", "hold,track_cascade", "--settle-deg", "-1"], "--settle-deg: "),
                         (["--methods", "hold,track", "--settle-deg", "2"], "applies to")):
        with pytest.raises(SystemExit):
            bench.main(base + extra)
        assert words in capsys.readouterr().err


# ------------------------------------------------------------------------------ the models that really ship
def _shipped():
    from refiner_rt import pretrained_models

    return pretrained_models()


@pytest.mark.skipif(not _shipped(), reason="no pretrained model ships in this checkout")
def test_every_shipped_model_tracks_by_name():
    """All shipped objects in one tracker, each by its name: one update refines each, unit wxyz with w >= 0."""
    names = [m.object_id for m in _shipped()]
    K_ycbv = np.array([[1066.8, 0, 313.0], [0, 1067.5, 241.3], [0, 0, 1]])
    image = np.random.default_rng(0).integers(0, 256, (480, 640, 3), dtype=np.uint8)
    tracker = RefinerTracker({n: n for n in names}, K_ycbv, {n: Q0[0] for n in names}, predict=True)
    for _ in range(3):
        out = tracker.update(image, {n: [250.0, 160.0, 390.0, 330.0] for n in names})
    assert sorted(out) == sorted(names)
    for q in out.values():
        assert q.shape == (4,) and np.isfinite(q).all() and abs(np.linalg.norm(q) - 1) < 1e-9 and q[0] >= 0


def test_tracker_takes_matrices_and_ros_ordered_quaternions_as_scipy_gives_them(tmp_path):
    """q0, add, reset and detector poses as (3, 3) matrices or xyzw quaternions track as the same rotations in wxyz."""
    from scipy.spatial.transform import Rotation

    from refiner_rt import RefinerSession
    from refiner_rt import quaternion as rq
    from tests.onnx_fixtures import constant_model

    sess = RefinerSession(constant_model([1, 0, 0, 0]))
    K = np.array([[500.0, 0, 80], [0, 500.0, 60], [0, 0, 1]])
    image = np.full((120, 160, 3), 90, np.uint8)
    rot = Rotation.random(2, random_state=3)
    wxyz = rq.from_xyzw(rot.as_quat())
    by_matrix = RefinerTracker(sess, K, {"003_cracker_box": rot[0].as_matrix()})
    by_xyzw = RefinerTracker(sess, K, {"003_cracker_box": rot[0].as_quat()}, q_order="xyzw")
    for t in (by_matrix, by_xyzw):
        q = t.update(image, {"003_cracker_box": [20, 20, 80, 90]})["003_cracker_box"]
        assert rq.geodesic_angle(q, wxyz[0]) < 1e-6
    by_xyzw.reset("003_cracker_box", rot[1].as_quat())
    by_matrix.add("003_cracker_box#2", rot[1].as_matrix())
    assert rq.geodesic_angle(by_xyzw.rotations["003_cracker_box"], wxyz[1]) < 1e-6
    assert rq.geodesic_angle(by_matrix.rotations["003_cracker_box#2"], wxyz[1]) < 1e-6
    with pytest.raises(ValueError, match="q_order must be one of"):
        RefinerTracker(sess, K, {}, q_order="zyxw")
    with pytest.raises(ValueError, match=r"is not a rotation matrix"):
        by_matrix.reset("003_cracker_box", 2 * np.eye(3))


def test_settle_deg_keeps_the_second_pass_where_it_turns_by_more(tmp_path):
    """The constant model turns by 7 degrees each pass: --settle-deg 5 keeps both passes of each update (two passes:
    --settle-deg runs at least two), 10 keeps the first only; the tracker refuses settle_deg with one pass."""
    import json

    from click.testing import CliRunner

    from refiner_rt.cli import main

    frames, dets, model = write_sequence(tmp_path, n=3)
    for settle, per_update in (("5", 2), ("10", 1)):
        out = tmp_path / f"rot{settle}.json"
        res = CliRunner().invoke(main, ["track", str(frames), str(dets), "-o", str(out), "--model", str(model),
                                        "--settle-deg", settle])
        assert res.exit_code == 0, res.output
        doc = json.loads(out.read_text())
        assert doc["settle_deg"] == float(settle) and doc["iterations"] == 2
        for i, name in enumerate(doc["frames"]):
            assert_same_rotation(np.array(doc["frames"][name]["003_cracker_box"]),
                                 scipy_q(Q0[0]) * scipy_q(Q_OUT) ** (per_update + HELD * i))
    res = CliRunner().invoke(main, ["track", str(frames), str(dets), "-o", str(out), "--model", str(model),
                                    "--settle-deg", "180"])
    assert res.exit_code == 2 and "--settle-deg" in res.output and "Traceback" not in res.output
    with pytest.raises(ValueError, match="give iterations=2 or more with it; got iterations=1"):
        _unfiltered(session(), K, {"003_cracker_box": Q0[0]}, settle_deg=2.0)
    tracker = _unfiltered(session(), K, {"003_cracker_box": Q0[0]}, iterations=3, settle_deg=10.0)
    q = tracker.update(IMG, {"003_cracker_box": BOX_A})["003_cracker_box"]
    assert_same_rotation(q, scipy_q(Q0[0]) * scipy_q(Q_OUT))


# ------------------------------------------------------------------------------ several starts per update
class TurnByBox:
    """A made-up session (the :class:`refiner_rt.Refiner` protocol) whose correction depends on the crop: each pass
    turns a row's rotation about the object's z axis by half the box's x1 in degrees, so every start's own box jitter shows
    in the result. Records each call's boxes and rotations."""

    per_call_passes = True

    def __init__(self, context=1.2):
        from types import SimpleNamespace

        self.contract = SimpleNamespace(objects=(OBJ,), crop_context=context)
        self.boxes, self.q_in = [], []

    def refine(self, image, boxes, q_in, *, K=None, D=None, coarse=None, iterations=1, views=1, settle_deg=None,
               q_order="wxyz"):
        q = rq.normalize(np.asarray(q_in, dtype=np.float64).reshape(-1, 4))
        b = np.asarray(boxes, dtype=np.float64).reshape(-1, 4)
        self.boxes.append(b)
        self.q_in.append(q)
        turn = rq.from_axis_angle(np.tile([0.0, 0.0, 1.0], (len(q), 1)), 0.5 * b[:, 0])
        out = q
        for _ in range(iterations):  # each pass turns by the same amount
            out = rq.multiply(out, turn)
        return RefineResult(q_refined=rq.canonical(out), q_out=turn, q_in=q)


def test_starts_average_refinements_from_turned_starts_on_their_own_box_jitters():
    """``starts=5``: one call of five rows per object, the first the track's rotation on its own box, the others turned
    15 degrees from it about four distinct axes (SciPy), each on a box of its own; the result is SciPy's mean of the
    five refinements, and the score counts their spread."""
    from refiner_rt.session import SCORE_SCALE_DEG
    from refiner_rt.tracker import START_DEG

    refiner = TurnByBox()
    tracker = _unfiltered({OBJ: refiner}, K, {OBJ: TRUTH}, starts=5)
    q = tracker.update(IMG, {OBJ: BOX_A})[OBJ]
    (boxes,), (q_in,) = refiner.boxes, refiner.q_in
    assert boxes.shape == (5, 4) and q_in.shape == (5, 4)
    np.testing.assert_allclose(boxes[0], BOX_A)
    assert len({tuple(b) for b in boxes.round(9)}) == 5  # each start on its own jitter
    start = scipy_q(TRUTH)
    assert_same_rotation(q_in[0], start)
    # the track's rotation turned in the object frame (right-multiplied) about a tetrahedron's axes: turns that balance
    tetrahedron = np.array([[1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]]) / np.sqrt(3.0)
    for s, axis in zip(q_in[1:], tetrahedron):
        assert_same_rotation(s, start * Rotation.from_rotvec(axis * np.radians(START_DEG)), atol=1e-9)
    refined = [scipy_q(s) * Rotation.from_rotvec([0.0, 0.0, np.radians(0.5 * b[0])]) for s, b in zip(q_in, boxes)]
    expected = Rotation.concatenate(refined).mean()
    assert_same_rotation(q, expected, atol=1e-9)
    spread = np.mean([(r * expected.inv()).magnitude() for r in refined])
    moved = (start.inv() * expected).magnitude()
    assert tracker.scores[OBJ] == pytest.approx(np.exp(-np.degrees(moved + spread) / SCORE_SCALE_DEG), rel=1e-6)


def test_starts_of_many_tracks_stay_within_the_batch_limit_and_match_one_track_at_a_time():
    """250 instances x 5 starts is more than MAX_BATCH crops: the update is split into calls within it, and every track
    gets what it gets when tracked alone."""
    from refiner_rt.checks import MAX_BATCH

    ids = [f"{OBJ}#{k}" for k in range(250)]
    starts = {i: rq.multiply(TRUTH, rq.from_axis_angle([1.0, 0.0, 0.0], 0.1 * k)) for k, i in enumerate(ids)}
    refiner = TurnByBox()
    out = RefinerTracker(refiner, K, starts, starts=5).update(IMG, {i: BOX_B for i in ids})
    assert max(len(b) for b in refiner.boxes) <= MAX_BATCH and len(refiner.boxes) >= 2
    for i in (ids[0], ids[137], ids[-1]):
        alone = RefinerTracker(TurnByBox(), K, {i: starts[i]}, starts=5).update(IMG, {i: BOX_B})[i]
        np.testing.assert_allclose(out[i], alone, atol=1e-12)


def test_a_cascade_refines_from_the_last_rotation_alone_with_starts():
    """A refiner that runs its own passes (a cascade) is refined from the track's rotation alone: ``starts`` is for
    sessions, as ``views`` is."""
    refiner = PullToTruthPerPass(TRUTH)
    tracker = RefinerTracker({OBJ: refiner}, K, {OBJ: rq.multiply(TRUTH, rq.from_axis_angle([0, 1.0, 0], 10.0))},
                             starts=5)
    q = tracker.update(IMG, {OBJ: BOX_A})[OBJ]
    assert refiner.calls == [1] and rq.geodesic_angle(q, TRUTH) < 1e-9


def test_nine_starts_turn_about_a_cube_s_corners_and_balance():
    """``starts=9``: the tetrahedron's four turns and the opposite four; the eight turns' rotation vectors sum to zero
    (the mean of the starts is the track's rotation)."""
    refiner = TurnByBox()
    _unfiltered({OBJ: refiner}, K, {OBJ: TRUTH}, starts=9).update(IMG, {OBJ: BOX_A})
    (q_in,) = refiner.q_in
    turns = Rotation.concatenate([scipy_q(TRUTH).inv() * scipy_q(s) for s in q_in[1:]])
    np.testing.assert_allclose(np.abs(turns.as_rotvec()), np.radians(15.0) / np.sqrt(3.0), atol=1e-9)
    np.testing.assert_allclose(turns.as_rotvec().sum(axis=0), 0.0, atol=1e-9)
    assert_same_rotation(Rotation.concatenate([scipy_q(s) for s in q_in]).mean().as_quat()[[3, 0, 1, 2]],
                         scipy_q(TRUTH), atol=1e-9)


def test_starts_with_views_stay_within_the_batch_limit():
    """Each start is refined with ``views`` crops: 60 tracks x 5 starts x 4 views = 1,200 crops go in calls whose rows
    times views stay within MAX_BATCH."""
    from refiner_rt.checks import MAX_BATCH

    ids = [f"{OBJ}#{k}" for k in range(60)]
    refiner = TurnByBox()
    RefinerTracker(refiner, K, {i: TRUTH for i in ids}, starts=5, views=4).update(IMG, {i: BOX_B for i in ids})
    assert len(refiner.boxes) == 2 and max(len(b) for b in refiner.boxes) * 4 <= MAX_BATCH


def test_a_start_s_jitter_the_runtime_would_refuse_is_the_box_itself():
    """A box mostly outside the image that update() accepts: the jitters that would fall below the inside share are
    replaced by the box itself, so the update refines instead of refusing a box it was not given."""
    from refiner_rt.checks import validate_boxes

    edge = [-14.5, 5.0, 6.0, 30.0]  # 29% of it inside the 64 x 48 image
    refiner = TurnByBox()
    RefinerTracker(refiner, K, {OBJ: TRUTH}, starts=9).update(IMG, {OBJ: edge})
    (boxes,) = refiner.boxes
    validate_boxes(boxes, IMG.shape)
    assert 1 < sum(np.allclose(b, edge) for b in boxes) < 9  # some jitters kept, some replaced


def test_starts_score_the_last_pass_with_several_iterations():
    """With ``iterations=2`` the score is RefineResult's calibrated one, from the last pass's correction (here each
    start's second pass turns it by half its box's x1 degrees) and the starts' spread, not from the whole turn."""
    from refiner_rt.session import SCORE_SCALE_DEG

    refiner = TurnByBox()
    tracker = _unfiltered({OBJ: refiner}, K, {OBJ: TRUTH}, starts=5, iterations=2)
    q = tracker.update(IMG, {OBJ: BOX_A})[OBJ]
    (boxes,), (q_in,) = refiner.boxes, refiner.q_in
    refined = [scipy_q(s) * Rotation.from_rotvec([0.0, 0.0, np.radians(b[0])]) for s, b in zip(q_in, boxes)]
    assert_same_rotation(q, Rotation.concatenate(refined).mean(), atol=1e-9)
    last = np.mean(0.5 * boxes[:, 0])  # every last pass about the object's z axis: their mean's angle
    spread = np.mean([np.degrees((r * Rotation.concatenate(refined).mean().inv()).magnitude()) for r in refined])
    assert tracker.scores[OBJ] == pytest.approx(np.exp(-(last + spread) / SCORE_SCALE_DEG), rel=1e-6)


def test_a_fused_detection_is_refined_from_its_own_starts():
    """With ``detector_weight`` the detection is refined beside the track, each from five starts in one call (10 rows):
    the result is w of the way from the track's mean to the detection's (SciPy's Slerp)."""
    from scipy.spatial.transform import Slerp

    refiner = TurnByBox()
    q_det = rq.multiply(TRUTH, rq.from_axis_angle([0.0, 1.0, 0.0], 20.0))
    tracker = RefinerTracker({OBJ: refiner}, K, {OBJ: TRUTH}, starts=5, detector_weight=0.5)
    q = tracker.update(IMG, {OBJ: BOX_A}, detector={OBJ: q_det})[OBJ]
    (boxes,), (q_in,) = refiner.boxes, refiner.q_in
    assert len(boxes) == 10
    assert_same_rotation(q_in[5], scipy_q(q_det))
    refined = [scipy_q(s) * Rotation.from_rotvec([0.0, 0.0, np.radians(0.5 * b[0])]) for s, b in zip(q_in, boxes)]
    track, det = Rotation.concatenate(refined[:5]).mean(), Rotation.concatenate(refined[5:]).mean()
    half = Slerp([0.0, 1.0], Rotation.concatenate([track, det]))([0.5])[0]
    assert_same_rotation(q, half, atol=1e-9)


@pytest.mark.parametrize("starts", [0, 2, 3, 10, True, 2.0, "5"])
def test_bad_starts_are_named(starts):
    with pytest.raises(ValueError, match="starts must be 1, 5 or 9"):
        RefinerTracker(session(), K, {"003_cracker_box": Q0[0]}, starts=starts)
