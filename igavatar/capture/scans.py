"""Ground-truth scans of a capture, matched to a dataset's test frames by name.

    gt_dir = default_gt_dir(dataset_dir, dataset_manifest)   # the capture's scans/
    matching = match_scans(gt_dir, test_frames, all_frames)
    vertices, faces = load_scan(matching.matched["frame_0001"])
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh

from igavatar.capture.capture_v1 import CAPTURE_FILE
from igavatar.capture.importers import detect_layout, read_layout
from igavatar.capture.xhumans import read_xhumans_scan
from igavatar.errors import InputError

#: Scan formats of a --gt folder; an imported capture (X-Humans) names its own scans (.pkl).
SCAN_SUFFIXES = (".ply", ".obj")


def existing(path: Path, beside: Path) -> Path | None:
    """`path` if it exists, else a sibling of `beside` with the same name (a moved run directory)."""
    if path.exists():
        return path
    sibling = beside.parent / path.name
    return sibling if sibling.exists() else None


@dataclass(frozen=True)
class ScanMatching:
    """Ground-truth scans matched to test frames by file stem.

    Attributes:
        matched: test frame -> scan path. missing: test frames with no scan.
        extra: scan stems that name no frame of the dataset. other_split: scan stems of dataset
        frames outside the test split (not evaluated). ignored_files: files that are not scans.
    """

    matched: dict[str, Path]
    missing: list[str]
    extra: list[str]
    other_split: list[str]
    ignored_files: list[str]

    def to_json(self) -> dict:
        return {"matched": sorted(self.matched), "missing": self.missing, "extra": self.extra,
                "other_split": self.other_split, "ignored_files": self.ignored_files}


def match_scans(gt_dir: Path, test_frames: list[str], all_frames: list[str]) -> ScanMatching:
    """Match `<gt_dir>/<frame>.ply|.obj` to the test frames; InputError if none matches.

    Args:
        gt_dir: directory of scans. test_frames: frames to evaluate, in order.
        all_frames: every frame of the dataset (to tell another split's scan from a stray one).
    """
    gt_dir = Path(gt_dir)
    if not gt_dir.is_dir():
        raise InputError(f"--gt {gt_dir}: no such directory of ground-truth scans (<frame>.ply or .obj)")
    scans: dict[str, Path] = {}
    ignored = []
    layout_scans = _layout_scans(gt_dir)
    if layout_scans is not None:
        scans = dict(layout_scans)
    for path in sorted(p for p in gt_dir.iterdir() if layout_scans is None and p.is_file() and not p.name.startswith(".")):
        if path.suffix.lower() not in SCAN_SUFFIXES:
            ignored.append(path.name)
            continue
        if path.stem in scans:
            raise InputError(
                f"--gt {gt_dir}: two scans for frame '{path.stem}' ({scans[path.stem].name} and {path.name}); keep one"
            )
        scans[path.stem] = path
    tests, known = set(test_frames), set(all_frames)
    matched = {f: scans[f] for f in test_frames if f in scans}
    if not matched:
        raise InputError(
            f"--gt {gt_dir}: no scan is named after a test frame (test frames: {', '.join(test_frames[:5])}"
            f"{', ...' if len(test_frames) > 5 else ''}; found {len(scans)} "
            f"{'scans in the capture' if layout_scans is not None else '.ply/.obj files'}); "
            "pass the scans folder of this capture, or --no-geometry"
        )
    return ScanMatching(
        matched=matched,
        missing=[f for f in test_frames if f not in scans],
        extra=sorted(s for s in scans if s not in known),
        other_split=sorted(s for s in scans if s in known and s not in tests),
        ignored_files=ignored,
    )


def _layout_scans(gt_dir: Path) -> dict[str, Path] | None:
    """frame -> scan of a capture in an imported layout that keeps its scans itself (X-Humans: one
    meshes_pkl/ folder per take), or None for a plain folder of <frame>.ply|.obj files."""
    if (gt_dir / CAPTURE_FILE).is_file():
        return None
    try:
        layout = detect_layout(gt_dir)
    except InputError:
        return None
    return read_layout(gt_dir, layout).scans


def load_scan(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (V, 3) float64 meters and faces (F, 3) int64 of a PLY/OBJ scan or an X-Humans mesh
    pickle; InputError if unusable."""
    if Path(path).suffix.lower() == ".pkl":
        return read_xhumans_scan(Path(path))
    try:
        mesh = trimesh.load(path, force="mesh", process=False)
    except Exception as exc:  # trimesh raises many types for a corrupt file; all mean "unreadable"
        raise InputError(f"{path}: cannot read the scan as a triangle mesh ({type(exc).__name__}: {exc})") from exc
    vertices = np.asarray(getattr(mesh, "vertices", np.zeros((0, 3))), np.float64)
    faces = np.asarray(getattr(mesh, "faces", np.zeros((0, 3))), np.int64)
    if vertices.ndim != 2 or vertices.shape[0] == 0 or faces.ndim != 2 or faces.shape[0] == 0:
        raise InputError(f"{path}: the scan has {len(vertices)} vertices and {len(faces)} faces; expected a triangle mesh")
    if not np.all(np.isfinite(vertices)):
        raise InputError(f"{path}: the scan has NaN or infinite vertex coordinates")
    return vertices, faces


def default_gt_dir(dataset_dir: Path, dataset_manifest: dict) -> Path:
    """`scans/` of the capture the dataset was made from (its manifest's first input)."""
    records = dataset_manifest.get("inputs", [])
    if not records:
        raise InputError(f"{dataset_dir}/manifest.json: no inputs recorded, so the capture is unknown; pass --gt")
    recorded = Path(records[0]["path"])
    # A capture without a manifest is recorded file by file: its first input is capture.json, or
    # for an imported layout a file in its root (whose scans match_scans finds by reading it).
    capture = recorded if records[0].get("artifact") == "capture" else recorded.parent
    found = existing(capture, dataset_dir)
    if found is None:
        raise InputError(
            f"{dataset_dir}/manifest.json: the capture {capture} it was made from does not exist; pass --gt SCANS_DIR"
        )
    if dataset_manifest.get("data", {}).get("source_format", "capture-v1") != "capture-v1":
        return found
    return found / "scans"
