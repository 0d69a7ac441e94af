"""refiner_rt.frames: the scan-frame / YCB-Video-frame translation, checked on mesh points (SciPy draws the poses)
and, where the shared folder is beside the repository, against the fit it records."""

import json
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from refiner_rt import frames
from refiner_rt.pretrained import pretrained_models


def test_the_same_point_lands_in_the_same_camera_place_in_both_frames():
    rng = np.random.default_rng(0)
    R = Rotation.random(5, random_state=2).as_matrix()
    t_ycbv = rng.uniform(-0.3, 0.3, (5, 3)) + [0, 0, 1.0]
    X_ycbv = rng.uniform(-0.1, 0.1, (5, 3))
    off = frames.ycbv_offset("003_cracker_box")
    X_scan = X_ycbv + off
    t_scan = frames.translation_from_ycbv("003_cracker_box", R, t_ycbv)
    np.testing.assert_allclose(np.einsum("nij,nj->ni", R, X_scan) + t_scan,
                               np.einsum("nij,nj->ni", R, X_ycbv) + t_ycbv, atol=1e-12)
    np.testing.assert_allclose(frames.translation_to_ycbv("003_cracker_box", R, t_scan), t_ycbv, atol=1e-12)


def test_every_shipped_object_has_an_offset_and_bad_input_is_named():
    for m in pretrained_models():
        assert np.linalg.norm(frames.ycbv_offset(m.object_id)) < 0.2  # a few centimetres
    with pytest.raises(ValueError, match="no frame offset for object 'nope'"):
        frames.ycbv_offset("nope")
    with pytest.raises(ValueError, match=r"R of shape \(..., 3, 3\)"):
        frames.translation_from_ycbv("003_cracker_box", np.eye(3), [1.0, 2.0])


def test_offsets_are_the_recorded_fit():
    source = Path(__file__).resolve().parents[2] / "shared" / "ycb_models" / "ycbv_frame_offsets.json"
    if not source.is_file():
        pytest.skip("the shared models folder is not beside the repository")
    fit = json.loads(source.read_text())["objects"]
    for obj, d in fit.items():
        np.testing.assert_allclose(frames.ycbv_offset(obj), d["t_translation_only_m"], atol=1e-6)
