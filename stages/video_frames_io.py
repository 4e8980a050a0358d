"""What every video capture does with its frames, whichever body poses them.

    frames, tracks = keep_frames(frames, tracks, tracks.detected, "no_person")   # drop, and say why
    write_frames(tmp, frames, tracks, camera)          # images/, masks/ (0/255) and cameras.npz
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from igavatar.artifacts.png import write_png
from igavatar.capture.person_landmarks import PersonTracks, person_mask
from igavatar.capture.video_fit import VideoCamera
from igavatar.capture.video_frames import VideoFrames


def keep_frames(frames: VideoFrames, tracks: PersonTracks, keep: np.ndarray,
                reason: str) -> tuple[VideoFrames, PersonTracks]:
    """The frames where `keep` (N,) bool holds; the others' source indices go to frames.dropped[reason]."""
    keep = np.asarray(keep, dtype=bool)
    if keep.all():
        return frames, tracks
    frames.dropped[reason] = [frames.source_indices[i] for i in np.flatnonzero(~keep)]
    rows = np.flatnonzero(keep)
    frames.images = [frames.images[i] for i in rows]
    frames.source_indices = [frames.source_indices[i] for i in rows]
    return frames, PersonTracks(tracks.detected[rows], tracks.masks[rows], tracks.people[rows], tracks.image_xy[rows],
                                tracks.visibility[rows], tracks.world_xyz[rows])


def write_frames(tmp: Path, frames: VideoFrames, tracks: PersonTracks, camera: VideoCamera) -> None:
    """images/<name>.png, masks/<name>.png (the tracked person, 0/255) and cameras.npz into `tmp`."""
    for sub in ("images", "masks"):
        (tmp / sub).mkdir()
    for name, image, probability in zip(frames.names, frames.images, tracks.masks):
        write_png(tmp / "images" / f"{name}.png", image)
        write_png(tmp / "masks" / f"{name}.png", person_mask(probability))
    np.savez(tmp / "cameras.npz", K=camera.K, w2c=camera.w2c, height=np.int64(camera.height), width=np.int64(camera.width))
