"""`igavatar view`: the rig's bone poses, the served page and scene, the slider, errors and Ctrl-C."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import threading
import urllib.request
from pathlib import Path

import numpy as np
import pytest
import viser

from igavatar.viewer.rig import ViewerRig
from igavatar_cli.main import app
from stages.view import ViewOptions, frame_image_reader, load_view, serve_view

REPO = Path(__file__).resolve().parents[1]


def _rotation(axis: np.ndarray, angle: float) -> np.ndarray:
    axis = axis / np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k


def _browser_skinning(rig: ViewerRig, wxyz: np.ndarray, positions: np.ndarray) -> np.ndarray:
    """What three.js does with the bones: sum_k w_k (current_b @ inverse(bind_b)) x, bind at the rig's bind poses."""
    bind_wxyz, bind_positions = rig.bind_poses()

    def matrix(q, p):
        m = np.eye(4)
        m[:3, :3] = viser.transforms.SO3(np.asarray(q, np.float64)).as_matrix()
        m[:3, 3] = p
        return m

    per_bone = np.stack([matrix(q, p) @ np.linalg.inv(matrix(bq, bp))
                         for q, p, bq, bp in zip(wxyz, positions, bind_wxyz, bind_positions)])
    blended = np.einsum("vk,vkab->vab", rig.top_weights, per_bone[rig.top_indices])
    x = np.concatenate([rig.vertices, np.ones((len(rig.vertices), 1))], axis=1)
    return np.einsum("vab,vb->va", blended, x)[:, :3]


def test_bone_poses_skin_the_mesh_as_the_browser_does():
    rng = np.random.default_rng(0)
    joints = rng.normal(size=(5, 3))
    weights = rng.random((40, 5)) ** 4
    rig = ViewerRig.build(rng.normal(size=(40, 3)), np.zeros((0, 3)), np.zeros((40, 3)), weights, joints,
                          np.array([-1, 0, 1, 1, 2]))
    transforms = np.tile(np.eye(4), (5, 1, 1))
    for b in range(5):
        transforms[b, :3, :3] = _rotation(rng.normal(size=3), rng.uniform(-2.5, 2.5))
        transforms[b, :3, 3] = rng.normal(size=3)
    wxyz, positions = rig.bone_poses(transforms)
    np.testing.assert_allclose(_browser_skinning(rig, wxyz, positions), rig.skin(transforms), atol=2e-5)
    # The four weights kept are each vertex's largest, renormalized.
    largest = np.sort(weights, axis=1)[:, -4:]
    np.testing.assert_allclose(np.sort(rig.top_weights, axis=1), largest / largest.sum(1, keepdims=True), rtol=1e-5)
    # Identity transforms leave the canonical mesh where it is.
    np.testing.assert_allclose(rig.skin(np.tile(np.eye(4), (5, 1, 1))), rig.vertices, atol=1e-6)


def test_view_content_of_a_tiny_model(tiny_model, small_run):
    content = load_view(ViewOptions(model=tiny_model, dataset=small_run / "dataset", mesh_resolution=32))
    assert content.frames.n_frames == 7 and content.frames.splits.count("test") == 3
    assert content.rig.faces.shape[0] > 100 and content.rig.colors.shape == content.rig.vertices.shape
    assert len(content.cameras) >= 1 and sum(len(c.frames) for c in content.cameras) == 7
    # The skeleton posed for a frame is the dataset's own posed joints.
    dataset_joints = content.dataset.frames().posed_joints
    np.testing.assert_allclose(content.rig.posed_joints(content.frames.bone_transforms[5]), dataset_joints[5], atol=1e-4)
    # The image shown on a frame's camera: that frame's photograph on white, as uint8.
    image = frame_image_reader(content)(5)
    assert image.dtype == np.uint8 and image.shape[:2] == content.dataset.image_size
    rgb, mask = content.dataset.image_and_mask(content.frames.names[5])
    np.testing.assert_array_equal(image[mask], rgb[mask])
    assert (image[~mask] == 255).all()


def test_view_reads_the_exported_mesh_and_its_texture_in_canonical_space(tiny_model, small_run, tmp_path):
    from stages.export import ExportOptions, run_export

    mesh = tmp_path / "mesh"
    run_export(ExportOptions(model=tiny_model, out=mesh, resolution=40, formats=("ply", "obj", "glb"), texture_size=128,
                             textured_faces=800, device="cpu"))
    content = load_view(ViewOptions(model=tiny_model, dataset=small_run / "dataset", mesh=mesh))
    assert content.facts["mesh"] == str(mesh / "canonical.ply") and content.textured is not None
    # The textured OBJ is written in glTF's frame; back in canonical space it covers the canonical mesh.
    box = lambda v: np.stack([np.min(v, axis=0), np.max(v, axis=0)])  # noqa: E731
    np.testing.assert_allclose(box(content.textured_rig.vertices), box(content.rig.vertices), atol=0.02)
    # On the page the texture is the first surface, and it poses with the frames.
    from igavatar.viewer.server import open_server, stop_server
    from stages.view import build_scene

    server = open_server(port=0)
    try:
        scene = build_scene(server, content, None)
        assert scene.surface.value == "texture"
        scene.set_frame(3)
        scene.surface.value = "colors"
        assert scene._posed is not None and scene.frame == 3
    finally:
        stop_server(server)


def _serve_in_thread(options: ViewOptions):
    ready, stop, box = threading.Event(), threading.Event(), {}

    def on_ready(server, scene):
        box["server"], box["scene"] = server, scene
        ready.set()

    thread = threading.Thread(target=lambda: box.setdefault("summary", serve_view(options, stop=stop, on_ready=on_ready)))
    thread.start()
    assert ready.wait(120), "the viewer did not come up"
    return box, stop, thread


def test_server_serves_the_page_and_the_slider_moves_the_bones(tiny_model, small_run, tmp_path):
    box, stop, thread = _serve_in_thread(ViewOptions(model=tiny_model, dataset=small_run / "dataset", port=0,
                                                     mesh_resolution=32, screenshots=tmp_path / "shots"))
    try:
        server, scene = box["server"], box["scene"]
        assert server.get_host() == "127.0.0.1" and server.get_port() > 0
        page = urllib.request.urlopen(f"http://127.0.0.1:{server.get_port()}/", timeout=30).read().decode()
        assert "<html" in page.lower() and "viser" in page.lower()
        before = np.array([bone.position for bone in scene.skinned.bones])
        scene.slider.value = 5  # what the page's slider sends
        after = np.array([bone.position for bone in scene.skinned.bones])
        assert np.abs(after - before).max() > 1e-3
        expected = scene.rig.bone_poses(scene.frames.bone_transforms[5])[1]
        np.testing.assert_allclose(after, expected, atol=1e-6)
        assert scene.frames.names[5] in scene.frame_label.content
        scene.canonical.value = True  # the bind pose: bones back at the canonical joints
        np.testing.assert_allclose([b.position for b in scene.skinned.bones], scene.rig.canonical_joints, atol=1e-6)
        scene.canonical.value = False
        scene.play.value = True  # the serving loop steps the slider at the fps
        for _ in range(100):
            if scene.frame != 5:
                break
            threading.Event().wait(0.05)
        scene.play.value = False
        assert scene.frame != 5
    finally:
        stop.set()
        thread.join(30)
    assert box["summary"]["frames"] == 7 and box["summary"]["url"].startswith("http://localhost:")


def _listening_socket() -> socket.socket:
    busy = socket.socket()
    busy.bind(("127.0.0.1", 0))
    busy.listen(1)
    return busy


def test_busy_port_is_one_line(cli_runner, tiny_model, small_run):
    busy = _listening_socket()
    try:
        port = busy.getsockname()[1]
        result = cli_runner.invoke(app, ["view", "--model", str(tiny_model), "--dataset", str(small_run / "dataset"),
                                         "--mesh-resolution", "32", "--port", str(port)])
    finally:
        busy.close()
    assert result.exit_code == 2
    assert f"--port {port}: already in use on 127.0.0.1" in result.output
    assert "Traceback" not in result.output


def test_missing_model_is_one_line(cli_runner, tmp_path):
    result = cli_runner.invoke(app, ["view", str(tmp_path / "no-run"), "--port", "0"])
    assert result.exit_code != 0
    assert "error:" in result.output and "no-run" in result.output and "Traceback" not in result.output


def test_ctrl_c_stops_the_server_cleanly(tiny_model, small_run, tmp_path):
    command = [sys.executable, "-m", "igavatar_cli.main", "view", "--model", str(tiny_model),
               "--dataset", str(small_run / "dataset"), "--mesh-resolution", "32", "--port", "0", "--json"]
    child = subprocess.Popen(command, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                             env={**os.environ, "PYTHONUNBUFFERED": "1", "COLUMNS": "200"})
    try:
        for line in child.stderr:
            if line.startswith("viewer: http://"):
                break
        else:
            pytest.fail("the viewer never printed its address")
        url = line.split()[1]
        assert urllib.request.urlopen(url, timeout=30).status == 200
        child.send_signal(signal.SIGINT)
        out, err = child.communicate(timeout=60)
    finally:
        child.kill()
    assert child.returncode == 0, err
    assert '"frames": 7' in out and "Traceback" not in err
    with pytest.raises(OSError):
        urllib.request.urlopen(url, timeout=5)


def test_scans_recorded_elsewhere_are_found_under_the_run(tmp_path):
    from stages.view import _recorded

    scan = tmp_path / "run" / "capture" / "scans" / "test_0000.ply"
    scan.parent.mkdir(parents=True)
    scan.write_text("ply")
    # eval ran from another folder: it recorded the path as given there
    assert _recorded(Path("somewhere/igavatar-run/capture/scans/test_0000.ply"), tmp_path / "run") == scan
    assert _recorded(Path("igavatar-run/capture/scans/missing.ply"), tmp_path / "run") is None


def test_unknown_motion_is_one_line(cli_runner, tiny_model, small_run):
    result = cli_runner.invoke(app, ["view", "--model", str(tiny_model), "--dataset", str(small_run / "dataset"),
                                     "--mesh-resolution", "32", "--motion", "moonwalk", "--port", "0"])
    assert result.exit_code == 2
    assert "--motion 'moonwalk': neither a procedural motion" in result.output and "Traceback" not in result.output
