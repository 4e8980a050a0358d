"""`igavatar validate PATH`: check an artifact (or a raw capture v1) against its schema and hashes.

    summary = validate_path(Path("igavatar-run/dataset"))   # ArtifactError / InputError if invalid

An artifact folder that also holds files its manifest does not list fails: they are not part of
it, and a later run refuses to replace the folder while they are there.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from igavatar.artifacts.manifest import MANIFEST_NAME, read_artifact, unlisted_files
from igavatar.avatar.dataset import read_dataset
from igavatar.avatar.model import load_model
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
        _read_arrays(path, manifest["artifact"])
        extra = unlisted_files(path, manifest)
        if extra:
            raise ArtifactError(
                f"{path}: holds {len(extra)} file(s) its manifest does not list ({', '.join(extra[:5])}"
                f"{', ...' if len(extra) > 5 else ''}); they are not part of the {manifest['artifact']} artifact, and "
                "igavatar refuses to replace a folder holding them: move them elsewhere"
            )
        return ValidationSummary(path, manifest["artifact"], manifest["schema_version"], len(manifest["outputs"]))
    if (path / CAPTURE_FILE).is_file():
        capture = read_capture_v1(path)
        return ValidationSummary(path, "capture (no manifest)", str(capture.meta["version"]), len(capture.frames))
    if not path.exists():
        raise ArtifactError(f"{path}: does not exist")
    raise ArtifactError(f"{path}: neither {MANIFEST_NAME} nor {CAPTURE_FILE} found; not an igavatar artifact")


def _read_arrays(path: Path, kind: str) -> None:
    """Read the arrays of a dataset or model as the stages will, checking every shape and dtype
    (a re-hashed file of the wrong shape passes the hash check)."""
    if kind == "dataset":
        dataset = read_dataset(path, check_hashes=False)
        dataset.frames()
    elif kind == "model":
        load_model(path)
