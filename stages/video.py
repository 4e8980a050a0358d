"""`igavatar preprocess --video`: a clip of one person -> a capture v1 artifact with fitted poses.

    summary = run_video_capture(VideoOptions(video=Path("clip.mp4"), out=Path("run/capture")))

Reads the frames (igavatar.capture.video_frames), finds the person and its landmarks with
MediaPipe (igavatar.capture.person_landmarks), checks the clip (one person, in frame, still
camera), fits Anny to the landmarks of the whole clip (igavatar.capture.video_fit) and writes a
capture that `preprocess` then reads like any other:

    images/frame_000123.png   the kept frames (named by their index in the source)
    masks/frame_000123.png    the tracked person's mask (0/255)
    cameras.npz               one fixed camera: K (3,3), w2c (4,4), height, width
    poses.npz                 Anny pose_parameters (N,104,4,4), phenotype labels and values
    landmarks.npz             BlazePose landmarks as fitted (after relabelling): image_xy (N,33,2),
                              visibility (N,33), world_xyz (N,33,3), fit_residual_px (N,33)
    capture.json              frames, splits (every --test-every-th frame held out), fps, and
                              "video": the source, kept and dropped frames, camera, body, fit
    contact_sheet.png         the fitted body (tinted, outlined) and skeleton over frames
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch

from igavatar.artifacts.atomic import atomic_directory
from igavatar.artifacts.manifest import InputRecord, build_manifest
from igavatar.artifacts.targets import check_output_target
from igavatar.artifacts.png import write_png
from igavatar.body.anny_body import AnnyBody, load_anny
from igavatar.body.skeleton import forward_kinematics
from igavatar.capture.contact_sheet import contact_sheet
from igavatar.capture.person_landmarks import LANDMARKS, PersonTracks, track_person
from igavatar.capture.video_checks import check_detections, check_in_frame, check_one_person, check_still_camera
from igavatar.capture.video_fit import (DEFAULT_HEIGHT_M, FREE_BONES, VideoCamera, anny_body_of_height, consistent_facing,
                                        fit_anny_to_tracks, relabelled)
from igavatar.capture.video_frames import IMAGE_SUFFIXES, FrameSelection, VideoFrames, read_video_frames
from igavatar.errors import InputError
from igavatar.geometry.projection import filled_silhouette, project_points
from stages.common import StageClock, unchanged
from stages.video_estimate import Estimate, estimate_meta, keep_estimated, place_estimate, read_estimate, write_estimate_capture
from stages.progress import NULL_PROGRESS, ProgressSink
from stages.resources import peak_ram_bytes
from stages.video_frames_io import keep_frames, write_frames

#: Fewer training frames than this cannot shape an avatar (the visual hull needs 8 views too).
MIN_TRAIN_FRAMES = 8
#: Bump when what the video path writes for the same clip and options changes.
VIDEO_FIT_VERSION = 2
SHEET_FRAMES = 12


@dataclass(frozen=True)
class VideoOptions:
    """Options of the video path (see `igavatar preprocess --help`)."""

    video: Path
    out: Path
    every: int = 1
    max_frames: int | None = 300
    test_every: int = 8
    height_m: float = DEFAULT_HEIGHT_M
    focal_px: float | None = None
    fov_deg: float | None = None
    max_side: int = 1024
    anny_cache: Path | None = None
    poses_from: Path | None = None
    """A GPU estimator's SMPL poses for the clip (WHAM, TRAM: stages.video_estimate), or None: igavatar's fit."""
    smpl_model: Path | None = None
    force: bool = False

    def config(self) -> dict:
        """What changes the capture (recorded in its manifest, compared to skip); the files are inputs."""
        config = asdict(self)
        for key in ("video", "out", "anny_cache", "force", "poses_from", "smpl_model"):
            config.pop(key)
        if self.poses_from is not None:
            config.pop("height_m")
            config["poses_from"] = "estimator"
        return {**config, "video_fit_version": VIDEO_FIT_VERSION}


def _check_options(options: VideoOptions) -> None:
    if options.every < 1:
        raise InputError(f"--every {options.every}: must be >= 1")
    if options.max_frames is not None and options.max_frames < MIN_TRAIN_FRAMES + 1:
        raise InputError(f"--max-frames {options.max_frames}: must be at least {MIN_TRAIN_FRAMES + 1}")
    if options.test_every < 0 or options.test_every == 1:
        raise InputError(f"--test-every {options.test_every}: 0 (no held-out frames) or >= 2")


def _input_records(video: Path, estimate: Estimate | None) -> list[InputRecord]:
    if video.is_dir():
        records = [InputRecord(p) for p in sorted(video.iterdir()) if p.suffix.lower() in IMAGE_SUFFIXES]
    elif not video.is_file():
        raise InputError(f"{video}: no such video file or folder of frames")
    else:
        records = [InputRecord(video)]
    if estimate is not None:
        records += [InputRecord(estimate.poses.path), InputRecord(estimate.model.path)]
    return records


def _splits(names: list[str], test_every: int) -> dict[str, list[str]]:
    """Every test_every-th frame (the k-th, 2k-th, ...) held out for eval; the rest train."""
    test = [n for i, n in enumerate(names) if test_every and (i + 1) % test_every == 0]
    held = set(test)
    return {"train": [n for n in names if n not in held], "test": test}


def _main_skeleton(body: AnnyBody) -> tuple[np.ndarray, np.ndarray]:
    """Joint indices of the fitted bones (and the root) and their parents within that subset, so
    the sheet shows the limbs that were fitted, not 60 finger and toe joints."""
    keep = [0] + [body.skeleton.index(bone) for bone in FREE_BONES]
    keep += [body.skeleton.index(bone) for bone in ("wrist.L", "wrist.R", "toe2-1.L", "toe2-1.R")]
    keep = sorted(set(keep))
    slot = {joint: i for i, joint in enumerate(keep)}
    parents = []
    for joint in keep:
        parent = int(body.skeleton.parents[joint])
        while parent >= 0 and parent not in slot:
            parent = int(body.skeleton.parents[parent])
        parents.append(slot.get(parent, -1))
    return np.array(keep), np.array(parents)


def _fitted_sheet(frames: VideoFrames, body: AnnyBody, fit, camera: VideoCamera) -> np.ndarray:
    """Contact sheet: the fitted body's silhouette and skeleton over up to SHEET_FRAMES frames."""
    picks = np.unique(np.linspace(0, len(frames.images) - 1, min(SHEET_FRAMES, len(frames.images))).round().astype(int))
    local = torch.as_tensor(fit.local_rotations[picks])
    translation = torch.as_tensor(fit.root_translation[picks])
    vertices = body.posed_vertices(local, translation).numpy()
    joints = forward_kinematics(local, body.skeleton.rest_joints, body.skeleton.parents, translation)[..., :3, 3].numpy()
    faces = body.faces.numpy()
    shown, parents = _main_skeleton(body)
    items = []
    for slot, index in enumerate(picks):
        joints_uv, _ = project_points(camera.K, camera.w2c, joints[slot][shown])
        items.append((frames.images[index], filled_silhouette(camera.K, camera.w2c, vertices[slot], faces, camera.height, camera.width), joints_uv,
                      f"{frames.names[index]} fitted"))
    return contact_sheet(items, parents)


def _fit(options: VideoOptions, frames: VideoFrames, tracks: PersonTracks, progress: ProgressSink):
    """Relabel back views, fit Anny; -> (body, camera, fit, flips (N,) bool, relabelled tracks)."""
    flips = consistent_facing(tracks.world_xyz)
    tracks = relabelled(tracks, flips)
    body = anny_body_of_height(AnnyBody(load_anny(options.anny_cache, on_status=progress.status)), options.height_m)
    height, width = frames.images[0].shape[:2]
    camera = VideoCamera.for_frames(height, width, options.focal_px, options.fov_deg)
    progress.status(f"fitting the body to {len(frames.images)} frames")
    return body, camera, fit_anny_to_tracks(body, tracks, camera, images=frames.images), flips, tracks


def _offsets_cm(offsets_m: np.ndarray) -> dict[str, list[float]]:
    """The clip's fitted landmark offsets (rest frame: +x the body's left, +z up), by landmark name,
    where any component reaches 1 mm."""
    return {name: [round(100 * float(v), 1) for v in offsets_m[index]] for name, index in LANDMARKS.items()
            if np.abs(offsets_m[index]).max() >= 1e-3}


def _meta_common(options: VideoOptions, frames: VideoFrames, background_px: float, body_model: str) -> dict:
    """capture.json's fields of any video capture: frames, splits, fps and what was kept and dropped."""
    names = frames.names
    return {
        "format": "igavatar-capture", "version": 1, "body_model": body_model, "frames": names,
        "splits": _splits(names, options.test_every), **({"fps": frames.fps} if frames.fps else {}),
        "image_ext": ".png", "source_format": "video",
        "video": {
            "source": str(options.video), "source_frames": frames.source_count,
            "source_size": list(frames.source_size), "kept_frames": len(names),
            "dropped": {reason: indices for reason, indices in frames.dropped.items()},
            "background_motion_px": round(background_px, 3),
        },
    }


def _meta(options: VideoOptions, frames: VideoFrames, body: AnnyBody, camera: VideoCamera, fit, flips: np.ndarray,
          background_px: float) -> dict:
    meta = _meta_common(options, frames, background_px, "anny")
    residual = fit.residual_px
    meta["video"].update({
        "relabelled_back_views": [frames.names[i] for i in np.flatnonzero(flips)],
        "camera": {"focal_px": float(camera.K[0, 0]), "focal_from": camera.focal_source,
                   "level": True, "image_size": [camera.height, camera.width]},
        "body": {"model": "anny", "height_m": options.height_m, "phenotype": dict(body.phenotype)},
        "fit": {"mean_residual_px": round(fit.mean_residual_px(), 3),
                "median_residual_px": round(float(np.nanmedian(residual)), 3),
                "frame_residual_px": [round(float(v), 2) for v in np.nanmean(residual, axis=1)],
                "landmark_offset_cm": _offsets_cm(fit.landmark_offsets),
                **({"silhouette": {k: round(v, 3) for k, v in fit.silhouette_px.items()}} if fit.silhouette_px else {})},
    })
    return meta


def _write_capture(tmp: Path, frames: VideoFrames, tracks: PersonTracks, body: AnnyBody, camera: VideoCamera, fit,
                   meta: dict) -> None:
    write_frames(tmp, frames, tracks, camera)
    pose_parameters = body.pose_parameters_from_local_rotations(torch.as_tensor(fit.local_rotations),
                                                                torch.as_tensor(fit.root_translation))
    np.savez(tmp / "poses.npz", pose_parameters=pose_parameters.numpy(),
             phenotype_labels=np.array(body.phenotype_labels, dtype=np.str_), phenotype_values=body.phenotype_values)
    np.savez(tmp / "landmarks.npz", image_xy=tracks.image_xy, visibility=tracks.visibility,
             world_xyz=tracks.world_xyz, fit_residual_px=fit.residual_px.astype(np.float32))
    sheet = _fitted_sheet(frames, body, fit, camera)
    write_png(tmp / "contact_sheet.png", sheet)
    (tmp / "capture.json").write_text(json.dumps(meta, indent=2) + "\n")


def run_video_capture(options: VideoOptions, progress: ProgressSink = NULL_PROGRESS) -> dict:
    """Make the capture of `options.video` at `options.out` (skipped when up to date); a summary.

    Raises InputError for a file that is no video, no person or two, a person cut by the frame,
    too few frames, or a moving camera; BodyModelError if Anny cannot be loaded.
    """
    _check_options(options)
    video, out = Path(options.video), Path(options.out)
    estimate = None if options.poses_from is None else read_estimate(options.poses_from, options.smpl_model)
    inputs = _input_records(video, estimate)
    if not options.force and unchanged(out, "capture", options.config(), inputs):
        return {"capture": str(out), "skipped": "video, options unchanged (use --force to redo)"}
    check_output_target(out, "capture", [video])
    clock = StageClock()
    with clock("read_s"):
        frames = read_video_frames(video, FrameSelection(options.every, options.max_frames, options.max_side))
    with clock("track_s"), progress.task("finding the person", total=len(frames.images)) as advance:
        tracks = track_person(frames.images, on_frame=lambda _: advance(1))
    check_detections(video, tracks, MIN_TRAIN_FRAMES + (1 if options.test_every else 0))
    frames, tracks = keep_frames(frames, tracks, tracks.detected, "no_person")
    if estimate is not None:
        frames, tracks = keep_estimated(frames, tracks, estimate.poses)
    if len(_splits(frames.names, options.test_every)["train"]) < MIN_TRAIN_FRAMES:
        raise InputError(f"{video}: {len(frames.names)} usable frames leave fewer than {MIN_TRAIN_FRAMES} to train "
                         "on; use a longer clip, a smaller --every, or --test-every 0")
    check_in_frame(video, tracks)
    check_one_person(video, tracks)
    background_px = check_still_camera(video, frames.images, tracks.masks)
    if estimate is not None:
        return _imported_capture(options, frames, tracks, estimate, background_px, clock, inputs)
    with clock("fit_s"):
        body, camera, fit, flips, tracks = _fit(options, frames, tracks, progress)
    meta = _meta(options, frames, body, camera, fit, flips, background_px)
    with atomic_directory(out, kind="capture", inputs=[video]) as tmp:
        with clock("write_s"):
            _write_capture(tmp, frames, tracks, body, camera, fit, meta)
        _manifest(tmp, options, meta, inputs, clock)
    return {**_summary(out, frames, clock), "fit_residual_px": round(fit.mean_residual_px(), 2)}


def _manifest(tmp: Path, options: VideoOptions, meta: dict, inputs: list[InputRecord], clock: StageClock) -> None:
    build_manifest("capture", tmp, stage="preprocess --video", config=options.config(), inputs=inputs, data=meta,
                   seed=None, device="cpu", timings=clock.finish(), peak_memory={"ram_bytes": peak_ram_bytes()})


def _summary(out: Path, frames: VideoFrames, clock: StageClock) -> dict:
    seconds = clock.elapsed()
    return {"capture": str(out), "frames": len(frames.names), "source_frames": frames.source_count,
            "seconds": round(seconds, 2), "seconds_per_frame": round(seconds / max(1, len(frames.names)), 3),
            "contact_sheet": str(out / "contact_sheet.png")}


def _imported_capture(options: VideoOptions, frames: VideoFrames, tracks: PersonTracks, estimate: Estimate,
                      background_px: float, clock: StageClock, inputs: list[InputRecord]) -> dict:
    """The capture with the estimator's SMPL poses in place of igavatar's Anny fit."""
    with clock("fit_s"):
        placed = place_estimate(estimate, frames, tracks, options.focal_px, options.fov_deg)
    meta = _meta_common(options, frames, background_px, "smpl")
    meta["video"].update(estimate_meta(estimate, placed))
    with atomic_directory(Path(options.out), kind="capture", inputs=[Path(options.video)]) as tmp:
        with clock("write_s"):
            write_estimate_capture(tmp, frames, tracks, estimate, placed, meta)
        _manifest(tmp, options, meta, inputs, clock)
    return {**_summary(Path(options.out), frames, clock), "poses_from": estimate.poses.estimator,
            "body_mask_iou": round(float(placed.body_mask_iou.mean()), 3)}
