"""EXR maps: bit-exact round trips, documented channel names, atomic writes, errors.

    .venv/bin/python -m pytest tests/test_exr.py -q
"""

from __future__ import annotations

import numpy as np
import OpenEXR
import pytest

from igavatar.errors import InputError
from igavatar.mesh.exr import read_exr, write_exr


def maps(height: int = 6, width: int = 5, seed: int = 0) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    depth = rng.uniform(0.5, 4.0, (height, width)).astype(np.float32)
    depth[0, 0] = np.inf  # background
    depth[0, 1] = np.nan
    normals = rng.normal(size=(height, width, 3)).astype(np.float32)
    normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
    return {
        "Z": depth,
        "N": normals,
        "RGB": rng.random((height, width, 3)).astype(np.float32),
        "A": (rng.random((height, width)) > 0.5).astype(np.float32),
    }


def test_round_trip_is_bit_exact(tmp_path):
    written = maps()
    path = tmp_path / "frame.exr"
    write_exr(path, written)
    read = read_exr(path)
    assert set(read) == set(written)
    for key, array in written.items():
        assert read[key].dtype == np.float32 and read[key].shape == array.shape
        np.testing.assert_array_equal(read[key].view(np.uint32), array.view(np.uint32))


def test_channel_names_follow_exr_conventions(tmp_path):
    path = tmp_path / "frame.exr"
    write_exr(path, maps())
    names = set(OpenEXR.File(str(path), separate_channels=True).channels())
    assert names == {"Z", "A", "R", "G", "B", "N.R", "N.G", "N.B"}
    # The components keep their order: N.R is x, N.G is y, N.B is z.
    raw = OpenEXR.File(str(path), separate_channels=True).channels()
    np.testing.assert_array_equal(raw["N.G"].pixels, maps()["N"][..., 1])


def test_reads_xyz_layers_written_by_other_tools(tmp_path):
    path = tmp_path / "other.exr"
    rng = np.random.default_rng(1)
    x, y, z, depth = (rng.random((3, 4)).astype(np.float32) for _ in range(4))
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    OpenEXR.File(header, {"normal.X": x, "normal.Y": y, "normal.Z": z, "depth.V": depth}).write(str(path))
    read = read_exr(path)
    assert set(read) == {"normal", "depth.V"}
    np.testing.assert_array_equal(read["normal"], np.stack((x, y, z), axis=-1))
    np.testing.assert_array_equal(read["depth.V"], depth)


def test_other_dtypes_become_float32(tmp_path):
    path = tmp_path / "cast.exr"
    mask = np.array([[True, False], [False, True]])
    depth64 = np.array([[0.1, 0.2], [0.3, 1e-9]])
    write_exr(path, {"mask": mask, "Z": depth64})
    read = read_exr(path)
    np.testing.assert_array_equal(read["mask"], mask.astype(np.float32))
    np.testing.assert_array_equal(read["Z"], depth64.astype(np.float32))


def test_write_is_atomic_and_overwrites(tmp_path):
    path = tmp_path / "sub" / "frame.exr"
    write_exr(path, {"Z": np.ones((2, 3), np.float32)})
    write_exr(path, {"Z": np.full((2, 3), 2.0, np.float32)})
    np.testing.assert_array_equal(read_exr(path)["Z"], 2.0)
    with pytest.raises(InputError, match="same size"):
        write_exr(path, {"Z": np.zeros((2, 3)), "N": np.zeros((3, 3, 3))})
    # The failed write left the previous file whole and no temporary files behind.
    np.testing.assert_array_equal(read_exr(path)["Z"], 2.0)
    assert [p.name for p in path.parent.iterdir()] == ["frame.exr"]


def test_bad_inputs_raise_input_error(tmp_path):
    path = tmp_path / "bad.exr"
    with pytest.raises(InputError, match="no channels"):
        write_exr(path, {})
    with pytest.raises(InputError, match=r"\(H, W\) or \(H, W, 3\)"):
        write_exr(path, {"N": np.zeros((2, 2, 4))})
    with pytest.raises(InputError, match="'R'"):
        write_exr(path, {"RGB": np.zeros((2, 2, 3)), "R": np.zeros((2, 2))})
    with pytest.raises(InputError, match="dtype"):
        write_exr(path, {"Z": np.array([["a", "b"]])})
    with pytest.raises(InputError, match="not found"):
        read_exr(tmp_path / "missing.exr")
    (tmp_path / "junk.exr").write_bytes(b"not an exr")
    with pytest.raises(InputError, match="not a readable OpenEXR"):
        read_exr(tmp_path / "junk.exr")
    assert not path.exists()
