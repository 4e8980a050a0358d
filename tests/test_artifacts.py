"""Artifacts: manifests validate, atomic writes never leave half-written results, readers refuse bad ones."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from igavatar.artifacts.atomic import atomic_directory
from igavatar.artifacts.manifest import InputRecord, build_manifest, read_artifact, sha256_file
from igavatar.errors import ArtifactError
from schemas import load_schema, schema_names

DATASET_DATA = {
    "source_format": "capture-v1", "body_model": "skeleton", "frames": ["a"], "splits": {"train": ["a"]},
    "image_size": [4, 4], "joint_names": ["root"], "pose_dim": 0,
    "skinning_grid": {"resolution": [2, 2, 2], "box_min": [0, 0, 0], "box_max": [1, 1, 1]},
    "canonical_box": [[0, 0, 0], [1, 1, 1]], "has_template": False,
}


def _write_dataset(target: Path, payload: bytes = b"abc", inputs=()) -> dict:
    with atomic_directory(target, kind="dataset") as tmp:
        (tmp / "sub").mkdir()
        (tmp / "sub" / "x.bin").write_bytes(payload)
        return build_manifest("dataset", tmp, stage="preprocess", config={"k": 1}, inputs=list(inputs), data=DATASET_DATA)


def test_every_artifact_kind_has_a_schema():
    names = schema_names()
    for kind in ("manifest", "capture", "dataset", "model", "mesh", "animation", "report"):
        assert kind in names
        assert load_schema(kind)["type"] == "object"


def test_round_trip_lists_and_verifies_every_file(tmp_path):
    manifest = _write_dataset(tmp_path / "ds")
    assert [o["path"] for o in manifest["outputs"]] == ["sub/x.bin"]
    assert manifest["outputs"][0]["sha256"] == sha256_file(tmp_path / "ds" / "sub" / "x.bin")
    again = read_artifact(tmp_path / "ds", expected="dataset")
    assert again == json.loads((tmp_path / "ds" / "manifest.json").read_text())
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")], "temporary directories left behind"


def test_input_records_hash_the_input_manifest(tmp_path):
    _write_dataset(tmp_path / "ds")
    manifest = _write_dataset(tmp_path / "ds2", inputs=[InputRecord(tmp_path / "ds", "dataset")])
    record = manifest["inputs"][0]
    assert record["sha256"] == sha256_file(tmp_path / "ds" / "manifest.json")
    assert record["artifact"] == "dataset" and record["schema_version"] == "1.0"


def test_edited_byte_is_a_hash_mismatch_naming_the_file(tmp_path):
    _write_dataset(tmp_path / "ds")
    path = tmp_path / "ds" / "sub" / "x.bin"
    path.write_bytes(b"abd")
    with pytest.raises(ArtifactError, match=r"x\.bin: sha256 mismatch.*igavatar preprocess"):
        read_artifact(tmp_path / "ds")


def test_missing_file_and_missing_manifest(tmp_path):
    _write_dataset(tmp_path / "ds")
    (tmp_path / "ds" / "sub" / "x.bin").unlink()
    with pytest.raises(ArtifactError, match="missing from the dataset artifact"):
        read_artifact(tmp_path / "ds")
    (tmp_path / "ds" / "manifest.json").unlink()
    with pytest.raises(ArtifactError, match="manifest.json: missing"):
        read_artifact(tmp_path / "ds")


def test_wrong_kind_names_both_kinds_and_the_maker(tmp_path):
    _write_dataset(tmp_path / "ds")
    with pytest.raises(ArtifactError, match=r"is a dataset artifact.*needs a model artifact made by `igavatar train`"):
        read_artifact(tmp_path / "ds", expected="model")


def test_other_major_version_is_refused(tmp_path):
    _write_dataset(tmp_path / "ds")
    path = tmp_path / "ds" / "manifest.json"
    manifest = json.loads(path.read_text())
    manifest["schema_version"] = "2.0"
    path.write_text(json.dumps(manifest))
    with pytest.raises(ArtifactError, match="schema version 2.0 is not readable"):
        read_artifact(tmp_path / "ds")


def test_manifest_schema_violation_names_the_field(tmp_path):
    _write_dataset(tmp_path / "ds")
    path = tmp_path / "ds" / "manifest.json"
    manifest = json.loads(path.read_text())
    del manifest["data"]["image_size"]
    path.write_text(json.dumps(manifest))
    with pytest.raises(ArtifactError, match="image_size"):
        read_artifact(tmp_path / "ds")


def test_failure_inside_block_keeps_the_previous_artifact(tmp_path):
    _write_dataset(tmp_path / "ds", payload=b"old")
    with pytest.raises(RuntimeError):
        with atomic_directory(tmp_path / "ds", kind="dataset") as tmp:
            (tmp / "partial.bin").write_bytes(b"half")
            raise RuntimeError("crash mid-stage")
    assert (tmp_path / "ds" / "sub" / "x.bin").read_bytes() == b"old"
    assert not (tmp_path / "ds" / "partial.bin").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ds"]
    read_artifact(tmp_path / "ds")


def test_keyboard_interrupt_inside_block_keeps_the_previous_artifact(tmp_path):
    _write_dataset(tmp_path / "ds", payload=b"old")
    with pytest.raises(KeyboardInterrupt):
        with atomic_directory(tmp_path / "ds", kind="dataset"):
            raise KeyboardInterrupt
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ds"]
    assert (tmp_path / "ds" / "sub" / "x.bin").read_bytes() == b"old"


def test_success_replaces_the_previous_artifact(tmp_path):
    _write_dataset(tmp_path / "ds", payload=b"old")
    _write_dataset(tmp_path / "ds", payload=b"new")
    assert (tmp_path / "ds" / "sub" / "x.bin").read_bytes() == b"new"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ds"]


def test_single_files_and_artifact_folders_get_the_usual_permissions(tmp_path):
    """mkstemp/mkdtemp make private temporaries; what is renamed into place follows the umask
    (a GLB served by a web server or shared with a team must be readable by others)."""
    import os
    import stat

    from igavatar.artifacts.atomic import atomic_write_bytes, current_umask

    old = os.umask(0o022)
    try:
        assert current_umask() == 0o022
        atomic_write_bytes(tmp_path / "avatar.glb", b"glTF")
        assert stat.S_IMODE((tmp_path / "avatar.glb").stat().st_mode) == 0o644
        with atomic_directory(tmp_path / "mesh", kind="mesh") as tmp:
            (tmp / "x.txt").write_text("x")
        assert stat.S_IMODE((tmp_path / "mesh").stat().st_mode) == 0o755
    finally:
        os.umask(old)


def test_png_writer_round_trips_and_fails_loudly(tmp_path, monkeypatch):
    """One PNG writer: RGB and gray (bool masks as 0/255) round-trip; a bad array is a ValueError
    and a refused write a StorageError naming the file (cv2.imwrite returned False and wrote nothing)."""
    import errno
    import os

    import cv2

    from igavatar.artifacts import atomic
    from igavatar.artifacts.png import write_png
    from igavatar.errors import StorageError

    rgb = np.random.default_rng(0).integers(0, 256, (5, 7, 3), dtype=np.uint8)
    write_png(tmp_path / "a" / "rgb.png", rgb)
    np.testing.assert_array_equal(cv2.cvtColor(cv2.imread(str(tmp_path / "a" / "rgb.png")), cv2.COLOR_BGR2RGB), rgb)
    mask = rgb[..., 0] > 127
    write_png(tmp_path / "mask.png", mask)
    np.testing.assert_array_equal(cv2.imread(str(tmp_path / "mask.png"), cv2.IMREAD_GRAYSCALE), mask * 255)
    with pytest.raises(ValueError, match=r"\(5, 7, 4\) uint8"):
        write_png(tmp_path / "bad.png", np.zeros((5, 7, 4), np.uint8))

    def full(fd, data):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(atomic.os, "fdopen", lambda fd, mode: type("F", (), {"__enter__": lambda s: s, "__exit__": lambda s, *a: False, "write": full})())
    with pytest.raises(StorageError, match="full.png: no space left"):
        write_png(tmp_path / "full.png", rgb)
    assert not (tmp_path / "full.png").exists()
