"""What a training run keeps between its attempts: the shape initialization (a cache keyed by what
decides it) and the checkpoint an interrupted run left (resumed only by the same run).

    key = shape_init_key(config, sha256_file(template), canonical_box)
    state, path = cached_shape_init(avatar, key, [work / "shape_init.npz", out / "shape_init.npz"])
    state = state or fit_shape(avatar, config, template, canonical_box, key, on_step)
    resumed = checkpoint_of_this_run(work / "checkpoint.npz", run_key, config_json, dataset_sha)
    log = TrainingLog.open(work / "training_log.csv", resume=True)   # rows kept across --resume
"""

from __future__ import annotations

import csv
import dataclasses
import io
import json
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from igavatar.artifacts.atomic import atomic_write_bytes
from igavatar.artifacts.manifest import sha256_json
from igavatar.errors import InputError
from igavatar.model.avatar import Avatar
from igavatar.training.checkpoint import load_state
from igavatar.training.config import TrainConfig
from igavatar.training.shape_init import fit_sdf_to_template, template_sdf_samples

#: Bump when the shape initialization's targets or optimization change, so that caches written
#: by an older version are not reused as if they were the same fit.
SHAPE_INIT_VERSION = 2


def shape_init_key(config: TrainConfig, template_sha: str | None, canonical_box: np.ndarray) -> str:
    """Everything that decides the shape initialization's result (the cache is reused only on a match)."""
    return sha256_json({"version": SHAPE_INIT_VERSION, "sdf": dataclasses.asdict(config.avatar.sdf),
                        "steps": config.shape_init_steps, "points": config.shape_init_points,
                        "template": template_sha, "canonical_box": np.asarray(canonical_box, np.float64).round(7).tolist(),
                        "seed": config.seed})


def cached_shape_init(avatar: Avatar, key: str, cache_paths: list[Path]) -> tuple[dict | None, Path | None]:
    """Load the first cached fit with `key` into the avatar's SDF; (its state, its path), or (None, None)."""
    for path in cache_paths:
        if path.is_file():
            cached = load_state(path)
            if cached.get("key") == key:
                avatar.sdf_field.load_state_dict(cached["sdf"])
                return cached, path
    return None, None


def fit_shape(avatar: Avatar, config: TrainConfig, template: Path, canonical_box: np.ndarray, key: str,
              on_step: Callable[[int, float], None] | None) -> dict:
    """Fit the SDF to the template mesh at `template` (when there is one and steps are asked for);
    returns {"key", "sdf"}: the fit, a copy that shares no storage with the live parameters
    (`state_dict()` returns views: saved after training they would hold the trained SDF)."""
    if template.is_file() and config.shape_init_steps > 0:
        import trimesh

        mesh = trimesh.load(template, process=False)
        targets = template_sdf_samples(np.asarray(mesh.vertices), np.asarray(mesh.faces), canonical_box, seed=config.seed)
        fit_sdf_to_template(avatar.sdf_field, targets, config.shape_init_steps, config.shape_init_points,
                            seed=config.seed, on_step=on_step)
    return {"key": key, "sdf": {name: value.detach().clone() for name, value in avatar.sdf_field.state_dict().items()}}


def config_differences(old: dict, new: dict, prefix: str = "") -> list[str]:
    """'key: old -> new' for every leaf of two resolved configs that differs (nested keys dotted)."""
    differences = []
    for key in sorted(set(old) | set(new)):
        a, b = old.get(key), new.get(key)
        if isinstance(a, dict) and isinstance(b, dict):
            differences += config_differences(a, b, f"{prefix}{key}.")
        elif a != b:
            differences.append(f"{prefix}{key}: {a} -> {b}")
    return differences


def checkpoint_of_this_run(checkpoint: Path, run_key: str, config_json: dict, dataset_sha: str) -> dict:
    """The checkpoint of an interrupted run with the same options and dataset; InputError naming the
    options that differ when it is another run's."""
    state = load_state(checkpoint)
    if state.get("run_key") == run_key:
        return state
    reasons = []
    if "config" in state:
        differences = config_differences(json.loads(state["config"]), config_json)
        if differences:
            reasons.append("options differ (checkpoint -> now): " + "; ".join(differences[:4])
                           + ("; ..." if len(differences) > 4 else ""))
        if state.get("dataset_sha256") not in (None, dataset_sha):
            reasons.append("the dataset changed since the checkpoint")
    detail = ", ".join(reasons) or "it was written with another configuration or dataset"
    raise InputError(f"--resume: {checkpoint} does not match this run: {detail}; "
                     "repeat the interrupted run's options, or start without --resume")


@dataclass
class TrainingLog:
    """training_log.csv rows (kept across --resume) and the checkpoint they are saved with."""

    path: Path
    rows: list[dict]

    @classmethod
    def open(cls, path: Path, resume: bool) -> TrainingLog:
        rows = list(csv.DictReader(io.StringIO(path.read_text()))) if resume and path.is_file() else []
        return cls(path, rows)

    def save(self) -> None:
        buffer = io.StringIO()
        if self.rows:
            writer = csv.DictWriter(buffer, fieldnames=list(self.rows[0]))
            writer.writeheader()
            writer.writerows(self.rows)
        atomic_write_bytes(self.path, buffer.getvalue().encode())
