"""The avatar's page: a skinned mesh on its skeleton, a frame slider, cameras, scans and errors.

    scene = AvatarScene(server, rig, frames, cameras=views, scans=scans, textured=textured)
    scene.set_frame(12)                 # what moving the slider does
    scene.step_playback()               # called by the serving loop: one frame on while "play" is on

Every GUI element is on the server (shared by every open tab), so a page opened later shows the
same frame. The "surface" menu shows the mesh:
    texture   the export's textured mesh (`export --texture-size`), posed here the same way: the
              default when there is one
    colors    the canonical mesh posed here with the rig's top-4 skinning, in its vertex colors;
              viser's skinned mesh takes a single color
    skinned   viser's skinned mesh (three.js SkinnedMesh): the browser skins it from the bone poses
All use the same four weights and bone poses (ViewerRig), so they coincide.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import trimesh
import viser

from igavatar.metrics.geometry import closest_points_on_mesh
from igavatar.metrics.report import error_colors
from igavatar.viewer.rig import ViewerRig

SKINNED = "skinned"
COLORS = "colors"
TEXTURE = "texture"
ERRORS = "errors"
#: How far beside the avatar (to the body's left) the current frame's scan is shown, meters.
SCAN_OFFSET_M = 0.9
#: Distance to the scan shown fully red in the "errors" surface (blue at 0, OpenCV's JET map).
ERROR_VMAX_MM = 20.0


@dataclass(frozen=True, eq=False)
class ViewerFrames:
    """The pose sequence the slider runs over: names (N,), bone_transforms (N, J, 4, 4) canonical ->
    posed world, fps, and the split of each frame ("train", "test" or "" for a motion)."""

    names: list[str]
    bone_transforms: np.ndarray
    fps: float
    splits: list[str] = field(default_factory=list)

    @property
    def n_frames(self) -> int:
        return len(self.names)


@dataclass(frozen=True, eq=False)
class CameraView:
    """One capture camera: K (3, 3), w2c (4, 4), image size (height, width), and the frames it saw."""

    K: np.ndarray
    w2c: np.ndarray
    size_hw: tuple[int, int]
    frames: tuple[int, ...]


def _wxyz_of(rotation: np.ndarray) -> np.ndarray:
    return viser.transforms.SO3.from_matrix(rotation).wxyz


class AvatarScene:
    """Builds the page on `server` and keeps it in step with the GUI."""

    def __init__(self, server: viser.ViserServer, rig: ViewerRig, frames: ViewerFrames, *, up: np.ndarray,
                 forward: np.ndarray,
                 cameras: list[CameraView] = (), frame_image=None, scans: dict[str, trimesh.Trimesh] | None = None,
                 textured: trimesh.Trimesh | None = None, textured_rig: ViewerRig | None = None,
                 screenshot_dir: Path | None = None):
        """up, forward: (3,) the body's world directions; frame_image(i) -> (H, W, 3) uint8 image of
        frame i (or None); scans: frame name -> world scan; textured: the baked-texture mesh in
        canonical space, skinned with textured_rig."""
        self.server, self.rig, self.frames = server, rig, frames
        self.cameras, self.frame_image = list(cameras), frame_image
        self.scans = scans or {}
        self.textured, self.textured_rig = textured, textured_rig
        self.screenshot_dir = screenshot_dir
        self.screenshots: list[Path] = []
        self._posed = self._scan = None  # the scene nodes re-made per frame (None: not shown)
        self._camera_handles: list = []
        self._camera_images: list[int | None] = []  # the frame whose image each camera shows (None: none)
        server.scene.set_up_direction(tuple(float(v) for v in up))
        # The scan stands beside the avatar, to the body's left: overlaid, the avatar's surface (made
        # ~3 beta outside the zero level) would hide it; the "errors" surface shows the overlap.
        self.scan_offset = SCAN_OFFSET_M * np.cross(np.asarray(up, np.float64), np.asarray(forward, np.float64))
        self._frame_the_subject(np.asarray(up, np.float64), np.asarray(forward, np.float64))
        self._add_gui()
        bind_wxyz, bind_positions = rig.bind_poses()
        self.skinned = server.scene.add_mesh_skinned(
            "/avatar/skinned", rig.vertices, rig.faces, bone_wxyzs=bind_wxyz, bone_positions=bind_positions,
            skin_weights=rig.skin_weights, color=(200, 170, 140), visible=False,
        )
        self._add_cameras()
        self.set_frame(0)

    def _frame_the_subject(self, up: np.ndarray, forward: np.ndarray) -> None:
        """A new page's camera: in front of the first frame's body, slightly above, the whole height in view."""
        joints = self.rig.posed_joints(self.frames.bone_transforms[0]).astype(np.float64)
        center = 0.5 * (joints.min(0) + joints.max(0))
        height = float(np.ptp(joints @ up)) + 0.3
        camera = self.server.initial_camera
        camera.up = tuple(up)
        camera.look_at = tuple(center)
        camera.position = tuple(center + forward * 0.9 * max(height, 1.0) + up * 0.1 * height)

    # ------------------------------------------------------------------------------------ GUI
    def _add_gui(self) -> None:
        gui, n = self.server.gui, self.frames.n_frames
        with gui.add_folder("Pose"):
            self.slider = gui.add_slider("frame", min=0, max=max(n - 1, 1), step=1, initial_value=0, disabled=n < 2)
            self.frame_label = gui.add_markdown("")
            self.play = gui.add_checkbox("play", initial_value=False)
            self.fps = gui.add_number("fps", initial_value=float(self.frames.fps), min=1.0, max=120.0, step=1.0)
            self.canonical = gui.add_checkbox("canonical pose", initial_value=False)
        with gui.add_folder("Show"):
            # The export's texture (from the images by default) is the sharpest picture there is: first when present.
            surfaces = ([TEXTURE] if self.textured is not None else []) + [COLORS, SKINNED]
            surfaces += [ERRORS] if self.scans else []
            self.surface = gui.add_dropdown("surface", tuple(surfaces), initial_value=surfaces[0])
            self.show_skeleton = gui.add_checkbox("skeleton", initial_value=True)
            self.show_cameras = gui.add_checkbox("cameras", initial_value=bool(self.cameras))
            self.show_scan = gui.add_checkbox("scan", initial_value=False, disabled=not self.scans)
        self.screenshot_button = gui.add_button("save screenshot", disabled=self.screenshot_dir is None)
        self.screenshot_note = gui.add_markdown("")

        self.slider.on_update(lambda _: self.set_frame(int(self.slider.value)))
        for control in (self.canonical, self.surface, self.show_skeleton, self.show_scan):
            control.on_update(lambda _: self.set_frame(self.frame))
        self.show_cameras.on_update(lambda _: self._show_cameras())
        self.screenshot_button.on_click(lambda event: self.save_screenshot(event.client))

    # ------------------------------------------------------------------------------------ frames
    @property
    def frame(self) -> int:
        return int(self.slider.value)

    def current_transforms(self) -> np.ndarray:
        """(J, 4, 4) of the frame shown: identity in the canonical pose."""
        if self.canonical.value:
            return np.broadcast_to(np.eye(4, dtype=np.float32), (self.rig.n_bones, 4, 4))
        return self.frames.bone_transforms[self.frame]

    def set_frame(self, index: int) -> None:
        """Show frame `index` (clamped): bones, posed surface, skeleton, scan and the camera image."""
        index = int(np.clip(index, 0, self.frames.n_frames - 1))
        if int(self.slider.value) != index:
            self.slider.value = index  # its on_update calls back here
            return
        transforms = self.current_transforms()
        name = self.frames.names[index]
        split = self.frames.splits[index] if self.frames.splits else ""
        self.frame_label.content = f"**{name}**" + (f" ({split})" if split else "") + (
            " - canonical pose" if self.canonical.value else "")
        with self.server.atomic():
            wxyz, positions = self.rig.bone_poses(transforms)
            for bone, q, p in zip(self.skinned.bones, wxyz, positions):
                bone.wxyz, bone.position = q, p
            self.skinned.visible = self.surface.value == SKINNED
            self._show_surface(transforms, name)
            self._show_skeleton(positions)
            self._show_scan(name)
            self._show_cameras()

    def step_playback(self) -> None:
        """One frame forward (wrapping) when "play" is on."""
        if self.play.value and self.frames.n_frames > 1:
            self.slider.value = (self.frame + 1) % self.frames.n_frames

    # ------------------------------------------------------------------------------------ layers
    def _show_surface(self, transforms: np.ndarray, name: str) -> None:
        surface = self.surface.value
        if surface == SKINNED:
            if self._posed is not None:
                self._posed.remove()
                self._posed = None
            return
        if surface == TEXTURE:
            mesh = self.textured.copy()
            mesh.vertices = self.textured_rig.skin(transforms)
        else:
            colors = self.rig.colors
            vertices = self.rig.skin(transforms)
            if surface == ERRORS:
                scan = None if self.canonical.value else self.scans.get(name)
                colors = np.full_like(self.rig.colors, 160)  # no scan for this frame: gray
                if scan is not None:
                    distance_m = closest_points_on_mesh(vertices, scan.vertices, scan.faces)[1]
                    colors = (error_colors(distance_m * 1000.0, ERROR_VMAX_MM) * 255).round().astype(np.uint8)
            mesh = trimesh.Trimesh(vertices, self.rig.faces, vertex_colors=colors, process=False)
        self._posed = self.server.scene.add_mesh_trimesh("/avatar/posed", mesh)

    def _show_skeleton(self, joints: np.ndarray) -> None:
        segments = self.rig.bone_segments(joints)
        self.server.scene.add_line_segments("/avatar/skeleton", segments, colors=(230, 60, 60), thickness=0.008,
                                            visible=bool(self.show_skeleton.value))

    def _show_scan(self, name: str) -> None:
        scan = self.scans.get(name)
        if self._scan is not None:
            self._scan.remove()
            self._scan = None
        if scan is None or not self.show_scan.value or self.canonical.value:
            return
        self._scan = self.server.scene.add_mesh_simple("/scan", np.asarray(scan.vertices, np.float32), np.asarray(scan.faces),
                                                       color=(150, 170, 210), position=self.scan_offset)

    def _add_cameras(self) -> None:
        for k, camera in enumerate(self.cameras):
            c2w = np.linalg.inv(camera.w2c)
            h, w = camera.size_hw
            fov = 2.0 * np.arctan2(h / 2.0, camera.K[1, 1])
            self._camera_handles.append(self.server.scene.add_camera_frustum(
                f"/cameras/{k}", fov=float(fov), aspect=w / h, scale=0.15, color=(40, 40, 40),
                wxyz=_wxyz_of(c2w[:3, :3]), position=c2w[:3, 3], visible=bool(self.show_cameras.value),
            ))
            self._camera_images.append(None)

    def _show_cameras(self) -> None:
        """Every camera (toggle); the current frame's image on the camera that took it (an image is
        sent only when a camera's changes)."""
        visible = bool(self.show_cameras.value)
        for k, (camera, handle) in enumerate(zip(self.cameras, self._camera_handles)):
            handle.visible = visible
            shown = self.frame if visible and self.frame_image is not None and self.frame in camera.frames else None
            if shown != self._camera_images[k]:
                handle.image = None if shown is None else self.frame_image(shown)
                self._camera_images[k] = shown

    # ------------------------------------------------------------------------------------ screenshot
    def save_screenshot(self, client: viser.ClientHandle, size_hw: tuple[int, int] = (720, 960)) -> Path:
        """The client's current view as a PNG in screenshot_dir; returns its path."""
        import imageio.v3 as iio

        image = np.asarray(client.get_render(height=size_hw[0], width=size_hw[1], transport_format="png"), np.float64)
        if image.shape[-1] == 4:  # the page's background is transparent in a render: on white, as the page shows it
            alpha = image[..., 3:] / 255.0
            image = image[..., :3] * alpha + 255.0 * (1.0 - alpha)
        self.screenshot_dir.mkdir(parents=True, exist_ok=True)
        path = self.screenshot_dir / f"view_{self.frames.names[self.frame]}_{len(self.screenshots):03d}.png"
        iio.imwrite(path, image[..., :3].round().astype(np.uint8))
        self.screenshots.append(path)
        self.screenshot_note.content = f"saved `{path}`"
        return path
