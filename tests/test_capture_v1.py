"""Capture v1 reading: a valid capture loads; each kind of bad input is one clear error naming the file/key."""

from __future__ import annotations

import json

import numpy as np
import pytest

from igavatar.capture.capture_v1 import load_image, load_mask, read_capture_v1
from igavatar.errors import InputError


def test_valid_capture_loads_with_per_frame_cameras(tiny_skeleton_capture):
    capture = read_capture_v1(tiny_skeleton_capture)
    assert capture.frames == ["f000", "f001", "f002"]
    assert capture.K.shape == (3, 3, 3) and capture.w2c.shape == (3, 4, 4)
    assert capture.has_masks and capture.body_model == "skeleton"
    image = load_image(capture.image_path("f001"), (capture.height, capture.width))
    assert image.shape == (16, 16, 3) and image.dtype == np.uint8 and image[0, 0, 0] == 40
    mask = load_mask(capture.mask_path("f001"))
    assert mask.dtype == bool and mask.sum() == 64


def test_missing_directory(tmp_path):
    with pytest.raises(InputError, match="no such capture directory"):
        read_capture_v1(tmp_path / "nope")


@pytest.mark.parametrize(
    "edit, message",
    [
        ({"format": "instant-avatar"}, "key 'format' is 'instant-avatar'"),
        ({"version": 2}, "key 'version' is 2"),
        ({"body_model": "mano"}, "unknown body model 'mano'"),
        ({"splits": {"train": ["zzz"]}}, "splits.train names frames not in 'frames'"),
    ],
)
def test_capture_json_of_another_format_version_or_model(tiny_skeleton_capture, edit, message):
    path = tiny_skeleton_capture / "capture.json"
    meta = json.loads(path.read_text())
    meta.update(edit)
    path.write_text(json.dumps(meta))
    with pytest.raises(InputError, match=message):
        read_capture_v1(tiny_skeleton_capture)


def test_pose_array_of_the_wrong_shape_names_key_and_shapes(tiny_skeleton_capture):
    path = tiny_skeleton_capture / "poses.npz"
    poses = dict(np.load(path))
    poses["rotvecs"] = np.zeros((3, 3))
    np.savez(path, **poses)
    with pytest.raises(InputError, match=r"poses\.npz: key 'rotvecs' has shape \(3, 3\), expected \(N, J, 3\)"):
        read_capture_v1(tiny_skeleton_capture)


def test_pose_frame_count_mismatch(tiny_skeleton_capture):
    path = tiny_skeleton_capture / "poses.npz"
    poses = dict(np.load(path))
    poses["transl"] = np.zeros((5, 3))
    np.savez(path, **poses)
    with pytest.raises(InputError, match=r"key 'transl' has shape \(5, 3\).*N=3"):
        read_capture_v1(tiny_skeleton_capture)


def test_fewer_masks_than_images(tiny_skeleton_capture):
    (tiny_skeleton_capture / "masks" / "f002.png").unlink()
    with pytest.raises(InputError, match=r"fewer masks \(2\) than images \(3\).*f002\.png"):
        read_capture_v1(tiny_skeleton_capture)


def test_image_that_is_not_an_image(tiny_skeleton_capture):
    capture = read_capture_v1(tiny_skeleton_capture)
    capture.image_path("f000").write_bytes(b"this is not a png")
    with pytest.raises(InputError, match=r"f000\.png: not a readable image"):
        load_image(capture.image_path("f000"))


def test_missing_camera_key_and_pickled_npz(tiny_skeleton_capture):
    np.savez(tiny_skeleton_capture / "cameras.npz", K=np.eye(3), height=16, width=16)
    with pytest.raises(InputError, match=r"cameras\.npz: key 'w2c' missing"):
        read_capture_v1(tiny_skeleton_capture)
    np.savez(tiny_skeleton_capture / "cameras.npz", K=np.array([{"a": 1}], dtype=object), w2c=np.eye(4), height=16, width=16)
    with pytest.raises(InputError, match="pickled objects"):
        read_capture_v1(tiny_skeleton_capture)


def test_non_rigid_w2c_is_refused(tiny_skeleton_capture):
    w2c = np.eye(4)
    w2c[0, 0] = 2.0
    np.savez(tiny_skeleton_capture / "cameras.npz", K=np.eye(3), w2c=w2c, height=16, width=16)
    with pytest.raises(InputError, match="not orthonormal"):
        read_capture_v1(tiny_skeleton_capture)
