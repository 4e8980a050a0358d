"""Capture layouts `preprocess` reads, by name: detection and reading (DATA.md section 1).

    name = detect_layout(Path("data/male-3-casual"))            # 'peoplesnapshot', ...
    capture = read_layout(Path("data/male-3-casual"), name)       # a validated CaptureV1

Every importer returns the native capture (`CaptureV1`) in memory: frames, cameras, the poses in
the capture v1 layout of its body model, splits, and each frame's image and mask file where that
layout keeps them. Importers live in their own modules and register here; detection asks each in
turn (the native layout first), so a directory is never claimed by two.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from igavatar.capture.capture_v1 import CAPTURE_FILE, CaptureV1, read_capture_v1
from igavatar.errors import InputError


@dataclass(frozen=True)
class Importer:
    """One capture layout.

    Attributes:
        name: the `--format` value.
        description: a few words for `--help` and errors.
        detect: root -> whether the directory looks like this layout (cheap: file names only).
        read: root -> a validated CaptureV1 (InputError naming the file/key/shape otherwise).
    """

    name: str
    description: str
    detect: Callable[[Path], bool]
    read: Callable[[Path], CaptureV1]


def _importers() -> list[Importer]:
    """The registered layouts, native first. Imported lazily so `--help` stays fast."""
    found = [Importer("capture-v1", "igavatar capture v1 (capture.json)",
                      lambda root: (root / CAPTURE_FILE).is_file(), read_capture_v1)]
    from igavatar.capture import peoplesnapshot, xhumans

    found.append(Importer(peoplesnapshot.NAME, "InstantAvatar/PeopleSnapshot (images/, cameras.npz, poses.npz)",
                          peoplesnapshot.detect_peoplesnapshot, peoplesnapshot.read_peoplesnapshot))
    found.append(Importer(xhumans.NAME, "X-Humans subject (mean_shape_smpl.npy, train|test/TakeN/)",
                          xhumans.detect_xhumans, xhumans.read_xhumans))
    from igavatar.capture import humannerf

    found.append(Importer("humannerf", "HumanNeRF / ZJU-MoCap monocular (cameras.pkl, mesh_infos.pkl)",
                          humannerf.detect_humannerf, humannerf.read_humannerf))
    return found


def layout_names() -> list[str]:
    """Every `--format` value but 'auto'."""
    return [importer.name for importer in _importers()]


def detect_layout(root: Path, requested: str = "auto") -> str:
    """The layout of `root`: `requested` unless 'auto', else the first importer that claims it."""
    importers = {importer.name: importer for importer in _importers()}
    if requested != "auto":
        if requested not in importers:
            raise InputError(f"--format {requested!r}: unknown; expected auto or one of {', '.join(layout_names())}")
        return requested
    if not root.exists():
        raise InputError(f"{root}: no such capture directory (make one with `igavatar synth` or `igavatar preprocess --video CLIP`, or pass --capture)")
    if not root.is_dir():
        raise InputError(f"{root}: is a file, expected a capture directory")
    for importer in importers.values():
        if importer.detect(root):
            return importer.name
    known = "; ".join(f"{i.name}: {i.description}" for i in importers.values())
    raise InputError(f"{root}: cannot detect the capture layout (pass --format; known layouts: {known})")


def read_layout(root: Path, name: str) -> CaptureV1:
    """Read `root` with the importer `name` (from detect_layout)."""
    importers = {importer.name: importer for importer in _importers()}
    if name not in importers:
        raise InputError(f"--format {name!r}: unknown; expected auto or one of {', '.join(importers)}")
    return importers[name].read(Path(root))
