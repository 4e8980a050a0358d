"""Artifact manifests: build, validate against `schemas/`, read back with hash checks.

    manifest = build_manifest("dataset", out_dir, stage="preprocess", config=cfg, inputs=[...], data={...})
    manifest = read_artifact(Path("runs/dataset"), expected="dataset")   # ArtifactError if wrong

Every artifact directory holds `manifest.json`; its `outputs` list the sha256 of every other file,
so a reader notices an edited, truncated or missing file and names it.
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import json
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import jsonschema

from igavatar import __version__
from igavatar.errors import ArtifactError
from schemas import load_schema

MANIFEST_NAME = "manifest.json"
#: The manifest field holding the sha256 of all its other fields (see `sealed`).
SEAL_KEY = "manifest_sha256"

#: Current MAJOR.MINOR layout version of each artifact kind; readers refuse another MAJOR.
SCHEMA_VERSIONS: dict[str, str] = {
    "capture": "1.0",
    "dataset": "1.0",
    "model": "1.0",
    "mesh": "1.0",
    "animation": "1.0",
    "report": "1.0",
}

#: The command that makes each kind, named in errors so a user knows what to (re)run.
PRODUCED_BY: dict[str, str] = {
    "capture": "igavatar synth or igavatar preprocess --video",
    "dataset": "igavatar preprocess",
    "model": "igavatar train",
    "mesh": "igavatar export",
    "animation": "igavatar animate",
    "report": "igavatar eval",
}


#: The command (and its input option) that makes each kind from the kind before it, suggested when
#: a user passes the earlier artifact where the later one is needed.
MADE_FROM: dict[str, tuple[str, str]] = {
    "dataset": ("capture", "igavatar preprocess --capture"),
    "model": ("dataset", "igavatar train --dataset"),
    "mesh": ("model", "igavatar export --model"),
    "animation": ("model", "igavatar animate --model"),
    "report": ("model", "igavatar eval --model"),
}

#: A raw capture v1 has this file but no manifest.
_CAPTURE_FILE = "capture.json"


def _make_it_hint(directory: Path, kind: str, expected: str) -> str:
    """'; make a dataset from it with `igavatar preprocess --capture DIR`' when `kind` is what makes `expected`."""
    source, command = MADE_FROM.get(expected, (None, None))
    if source != kind:
        return ""
    return f"; make a {expected} from it with `{command} {directory}`"


def sha256_file(path: Path, chunk_bytes: int = 1 << 20) -> str:
    """Hex sha256 of a file's bytes."""
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(chunk_bytes):
            digest.update(block)
    return digest.hexdigest()


def sha256_json(value: Any) -> str:
    """Hex sha256 of a JSON value in canonical form (sorted keys), e.g. a resolved config."""
    text = json.dumps(value, sort_keys=True, separators=(",", ":"), default=str)
    return hashlib.sha256(text.encode("utf-8")).hexdigest()


def _validation_message(error: jsonschema.ValidationError) -> str:
    where = ".".join(str(p) for p in error.absolute_path) or "(top level)"
    return f"{where}: {error.message}"


def first_schema_error(schema_name: str, value: Any) -> str | None:
    """'field.path: message' of the first way `value` fails schema `schema_name`, or None if valid."""
    validator = jsonschema.Draft202012Validator(load_schema(schema_name))
    errors = sorted(validator.iter_errors(value), key=lambda e: list(e.absolute_path))
    return _validation_message(errors[0]) if errors else None


def validate_against(schema_name: str, value: Any, what: str) -> None:
    """Raise ArtifactError naming `what` and the first offending field if `value` fails the schema."""
    error = first_schema_error(schema_name, value)
    if error is not None:
        raise ArtifactError(f"{what} does not match schema {schema_name}: {error}")


@dataclass(frozen=True)
class InputRecord:
    """One input of a stage: a file, or another artifact (hash of its manifest)."""

    path: Path
    artifact: str | None = None

    def to_json(self) -> dict:
        record: dict[str, Any] = {"path": str(self.path)}
        if self.artifact is not None:
            manifest_path = self.path / MANIFEST_NAME
            record["sha256"] = sha256_file(manifest_path)
            record["artifact"] = self.artifact
            record["schema_version"] = json.loads(manifest_path.read_text())["schema_version"]
        elif self.path.is_dir():
            raise ValueError(f"input {self.path} is a directory but no artifact kind was given")
        else:
            record["sha256"] = sha256_file(self.path)
        return record


def build_manifest(
    artifact: str,
    directory: Path,
    *,
    stage: str,
    config: dict,
    inputs: list[InputRecord],
    data: dict,
    seed: int | None = None,
    device: str = "cpu",
    timings: dict[str, float] | None = None,
    peak_memory: dict[str, float | None] | None = None,
) -> dict:
    """Hash every file under `directory`, assemble and validate the manifest, write it there.

    Call this last, inside `atomic_directory`, once every output file is written.
    """
    outputs = []
    for path in sorted(p for p in Path(directory).rglob("*") if p.is_file()):
        rel = path.relative_to(directory).as_posix()
        if rel == MANIFEST_NAME:
            continue
        outputs.append({"path": rel, "sha256": sha256_file(path), "bytes": path.stat().st_size})
    manifest = {
        "artifact": artifact,
        "schema_version": SCHEMA_VERSIONS[artifact],
        "tool_version": __version__,
        "created": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
        "stage": stage,
        "config": config,
        "inputs": [record.to_json() for record in inputs],
        "outputs": outputs,
        "seed": seed,
        "device": device,
        "timings": dict(timings or {}),
        "peak_memory": dict(peak_memory or {}),
        "data": data,
    }
    manifest = sealed(json.loads(json.dumps(manifest, default=str)))
    validate_against("manifest", manifest, f"{directory}/{MANIFEST_NAME}")
    validate_against(artifact, data, f"{directory}/{MANIFEST_NAME} (data)")
    (Path(directory) / MANIFEST_NAME).write_text(json.dumps(manifest, indent=2) + "\n")
    return manifest


def _content_sha256(manifest: dict) -> str:
    return sha256_json({key: value for key, value in manifest.items() if key != SEAL_KEY})


def sealed(manifest: dict) -> dict:
    """The manifest with its seal: the sha256 of every other field, so that an edit of any of them
    (config.max_size, data.splits) is noticed as the file hashes notice an edited file."""
    return {**{key: value for key, value in manifest.items() if key != SEAL_KEY}, SEAL_KEY: _content_sha256(manifest)}


def read_manifest(directory: Path) -> dict:
    """Parse and schema-check `directory/manifest.json` (no hash checks); ArtifactError if bad."""
    directory = Path(directory)
    if not directory.is_dir():
        raise ArtifactError(f"{directory}: no such artifact directory")
    path = directory / MANIFEST_NAME
    if not path.is_file():
        raise ArtifactError(f"{path}: missing; {directory} is not an igavatar artifact (or it was not finished)")
    try:
        manifest = json.loads(path.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ArtifactError(f"{path}: not valid JSON ({exc}); re-create the artifact") from exc
    validate_against("manifest", manifest, str(path))
    return manifest


def read_artifact(directory: Path, expected: str | None = None, *, check_hashes: bool = True) -> dict:
    """Read an artifact's manifest and check kind, major version, schema and file hashes.

    Args:
        directory: the artifact directory.
        expected: the artifact kind the caller needs, or None to accept any kind.
        check_hashes: verify the sha256 of every listed output file.
    Returns:
        the manifest dict.
    Raises:
        ArtifactError naming the file and the stage that makes the artifact.
    """
    directory = Path(directory)
    if expected not in (None, "capture") and not (directory / MANIFEST_NAME).is_file() and (directory / _CAPTURE_FILE).is_file():
        raise ArtifactError(
            f"{directory} is a capture (capture.json, no manifest), but this step needs a {expected} artifact"
            + (_make_it_hint(directory, "capture", expected) or f" made by `{PRODUCED_BY[expected]}`")
        )
    manifest = read_manifest(directory)
    kind = manifest["artifact"]
    maker = PRODUCED_BY[kind]
    if expected is not None and kind != expected:
        raise ArtifactError(
            f"{directory} is a {kind} artifact (made by `{maker}`), "
            f"but this step needs a {expected} artifact made by `{PRODUCED_BY[expected]}`"
            + _make_it_hint(directory, kind, expected)
        )
    major = manifest["schema_version"].split(".")[0]
    current_major = SCHEMA_VERSIONS[kind].split(".")[0]
    if major != current_major:
        raise ArtifactError(
            f"{directory / MANIFEST_NAME}: {kind} schema version {manifest['schema_version']} is not readable by "
            f"igavatar {__version__} (needs {current_major}.x); re-run `{maker}`"
        )
    validate_against(kind, manifest["data"], f"{directory / MANIFEST_NAME} (data)")
    if check_hashes:
        # Artifacts written before manifests were sealed have no seal: their file hashes are still checked.
        if SEAL_KEY in manifest and manifest[SEAL_KEY] != _content_sha256(manifest):
            raise ArtifactError(f"{directory / MANIFEST_NAME}: was edited after it was written (its fields no longer "
                                f"match its {SEAL_KEY}); re-run `{maker}`, or restore the original manifest.json")
        for output in manifest["outputs"]:
            path = directory / output["path"]
            if not path.is_file():
                raise ArtifactError(f"{path}: missing from the {kind} artifact; re-run `{maker}`")
            if sha256_file(path) != output["sha256"]:
                raise ArtifactError(
                    f"{path}: sha256 mismatch (the file was modified or corrupted); re-run `{maker}`"
                )
            problem = container_problem(path)
            if problem is not None:
                raise ArtifactError(f"{path}: corrupt {kind} artifact file ({problem}); re-run `{maker}`")
    return manifest


#: Files a desktop's file browser leaves in any folder it shows: not the user's work.
DESKTOP_LITTER = frozenset({".DS_Store", "Thumbs.db", "desktop.ini"})


def unlisted_files(directory: Path, manifest: dict) -> list[str]:
    """Files under an artifact directory that its manifest does not list (relative posix paths).

    Someone put them there after the artifact was written (a .blend file, renders); replacing the
    artifact would delete them. Desktop litter (.DS_Store, Thumbs.db) does not count.
    """
    listed = {output["path"] for output in manifest["outputs"]} | {MANIFEST_NAME}
    return sorted(rel for rel in (p.relative_to(directory).as_posix() for p in Path(directory).rglob("*")
                                  if p.is_file() or p.is_symlink())
                  if rel not in listed and rel.rsplit("/", 1)[-1] not in DESKTOP_LITTER)


def container_problem(path: Path) -> str | None:
    """Why a file with a matching hash still cannot be read (a truncated .npz or .png), or None.

    The hash only proves the file is the one the manifest lists; a manifest rewritten after the
    file was damaged lists the damage. Readers would then fail deep inside numpy or OpenCV, so
    the containers are checked here, cheaply: every member of an npz (zip CRCs) and a PNG's
    signature and end chunk.
    """
    suffix = path.suffix.lower()
    if suffix == ".npz":
        try:
            with zipfile.ZipFile(path) as archive:
                bad = archive.testzip()
        except (zipfile.BadZipFile, OSError, EOFError, ValueError) as exc:
            return f"not a readable npz: {exc}"
        return None if bad is None else f"npz member {bad} fails its CRC"
    if suffix == ".png":
        with open(path, "rb") as f:
            head = f.read(8)
            f.seek(0, 2)
            size = f.tell()
            f.seek(max(0, size - 12))
            tail = f.read()
        if head != b"\x89PNG\r\n\x1a\n" or b"IEND" not in tail:
            return "not a complete PNG (truncated or overwritten)"
    return None
