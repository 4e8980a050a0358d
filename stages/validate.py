"""`igavatar validate PATH`: check an artifact (or a raw capture v1) against its schema and hashes.

    summary = validate_path(Path("igavatar-run/dataset"))   # ArtifactError / InputError if invalid
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from igavatar.artifacts.manifest import MANIFEST_NAME, read_artifact
from igavatar.capture.capture_v1 import CAPTURE_FILE, read_capture_v1
from igavatar.errors import ArtifactError


@dataclass(frozen=True)
class ValidationSummary:
    """What was checked: the kind, its schema version and how many files were hashed."""

    path: Path
    kind: str
    schema_version: str
    files_checked: int


def validate_path(path: Path) -> ValidationSummary:
    """Validate an artifact directory, or a capture v1 that has no manifest of its own."""
    path = Path(path)
    if (path / MANIFEST_NAME).is_file():
        manifest = read_artifact(path)
        if manifest["artifact"] == "capture":
            read_capture_v1(path)
        return ValidationSummary(path, manifest["artifact"], manifest["schema_version"], len(manifest["outputs"]))
    if (path / CAPTURE_FILE).is_file():
        capture = read_capture_v1(path)
        return ValidationSummary(path, "capture (no manifest)", str(capture.meta["version"]), len(capture.frames))
    if not path.exists():
        raise ArtifactError(f"{path}: does not exist")
    raise ArtifactError(f"{path}: neither {MANIFEST_NAME} nor {CAPTURE_FILE} found; not an igavatar artifact")
