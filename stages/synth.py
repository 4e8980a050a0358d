"""`igavatar synth`: a synthetic monocular capture (capture v1) of a clothed, textured Anny subject.

    summary = run_synth(SynthOptions(out=Path("igavatar-run/capture")), progress=NULL_PROGRESS)
    capture = read_capture_v1(Path(summary["path"]))

Training frames: one 360-degree turn in place in the A-pose with small natural motion; test frames:
novel poses (walk in place, arm raise, squat), each turned by a seeded yaw. One static level camera
about 3 m away frames every frame. Per frame: images/<f>.png, masks/<f>.png (coverage > 0.5 of the
same 2x2 supersampled rays) and scans/<f>.ply (the posed clothed surface in world coordinates);
once, ground_truth/clothed_rest.npz (that surface in the rest pose with its skinning weights).
"""

from __future__ import annotations

import json
import resource
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import trimesh

from igavatar.artifacts.atomic import atomic_directory
from igavatar.artifacts.manifest import build_manifest
from igavatar.artifacts.targets import check_output_target
from igavatar.artifacts.png import write_png
from igavatar.body.anny_body import ANNY_PHENOTYPE_LABELS, AnnyBody, load_anny, resolve_phenotype
from igavatar.body.motions import Motion, motion_by_name, turntable, walk
from igavatar.body.rotations import rigid_matrix
from igavatar.body.skeleton import forward_kinematics, linear_blend_skinning
from igavatar.errors import InputError
from igavatar.geometry.mesh_ops import vertex_normals
from igavatar.geometry.raycast import CameraRays, MeshRayCaster, RayHits, interpolate_vertex_values, render_mesh
from igavatar.metrics.canonical import REST_SURFACE_FILE
from igavatar.synth.garments import GARMENTS, ClothedSubject, build_clothed_subject
from igavatar.synth.scene import frame_static_camera, lambert_shading, light_position, yaw_about_vertical
from igavatar.synth.skeleton_capture import bare_skeleton_poses, root_only_poses
from igavatar.synth.texture import TEXTURES, SolidTexture, find_landmarks, make_texture, region_ids
from stages.common import StageClock, unchanged
from stages.progress import NULL_PROGRESS, ProgressSink

#: Frames per second of the training turn (and the capture's nominal fps).
TRAIN_FPS = 30.0
#: Test motions, their duration in seconds (sampled by however many frames each gets) and yaw range.
TEST_MOTIONS: tuple[tuple[str, float, tuple[float, float]], ...] = (
    ("walk", 2.0, (0.6, 1.2)),
    ("arm_raise", 2.0, (-0.4, 0.4)),
    ("squat", 2.5, (0.3, 0.8)),
)
#: How `synth` writes the poses: with the body model, as its bare skeleton, or as one root joint.
SKELETONS = ("anny", "bare", "root")
CAMERA_DISTANCE_M = 3.0
SUPERSAMPLE = 2
BACKGROUND = (0.0, 0.0, 0.0)


@dataclass(frozen=True)
class SynthOptions:
    """Options of `igavatar synth`.

    Attributes:
        out: capture directory to write.
        resolution: image height and width in pixels.
        train_frames: frames of the 360-degree turn (training split).
        test_frames: frames of novel poses, split over walk, arm raise and squat (test split).
        holdout_frames: frames of a second A-pose turn (other small motions, views half-way
            between the training views) added to the test split as `test_holdout_*`: in-distribution
            poses for evaluation (0 = none, the default).
        phenotype: Anny phenotype overrides as "label=value" strings, values in [0, 1].
        garment: outfit, one of igavatar.synth.garments.GARMENTS.
        texture: texture style, one of igavatar.synth.texture.TEXTURES.
        seed: seeds colors, printed text, motion jitter and test-motion yaw.
        skeleton: how the poses are written (see SKELETONS): "anny" (the body model, the default),
            "bare" (Anny's joints as a bare skeleton, no body model: the skeleton-only path), or
            "root" (a static subject: one root joint, the body held still in the A-pose while
            it turns; no novel-pose test frames).
        anny_cache: Anny cache directory (None: $ANNY_CACHE_DIR or ~/.cache/anny).
        force: rewrite even if `out` already holds a capture made with the same config.
    """

    out: Path
    resolution: int = 512
    train_frames: int = 100
    test_frames: int = 30
    holdout_frames: int = 0
    phenotype: tuple[str, ...] = ()
    garment: str = "shirt-trousers"
    texture: str = "stripes"
    seed: int = 0
    skeleton: str = "anny"
    anny_cache: Path | None = None
    force: bool = False


def parse_phenotype(items: tuple[str, ...] | list[str]) -> dict[str, float]:
    """Full Anny phenotype from "label=value" strings; InputError names the bad item and valid labels."""
    overrides: dict[str, float] = {}
    for item in items:
        label, sep, text = str(item).partition("=")
        label = label.strip()
        if not sep or not label:
            raise InputError(
                f"--phenotype {item!r}: expected label=value, e.g. gender=0.3 (labels: {', '.join(ANNY_PHENOTYPE_LABELS)})"
            )
        if label not in ANNY_PHENOTYPE_LABELS:
            raise InputError(
                f"--phenotype {item!r}: unknown label {label!r}; valid labels: {', '.join(ANNY_PHENOTYPE_LABELS)}"
            )
        try:
            value = float(text)
        except ValueError as exc:
            raise InputError(f"--phenotype {item!r}: value {text!r} is not a number in [0, 1]") from exc
        if not np.isfinite(value) or not 0.0 <= value <= 1.0:
            raise InputError(f"--phenotype {item!r}: value {value} is outside [0, 1]")
        overrides[label] = value
    return resolve_phenotype(overrides)


def _check_options(options: SynthOptions) -> None:
    if options.resolution < 16:
        raise InputError(f"--resolution {options.resolution}: expected at least 16 pixels")
    if options.train_frames < 1:
        raise InputError(f"--train-frames {options.train_frames}: expected at least 1")
    if options.test_frames < 0:
        raise InputError(f"--test-frames {options.test_frames}: expected 0 or more")
    if options.holdout_frames < 0:
        raise InputError(f"--holdout-frames {options.holdout_frames}: expected 0 or more")
    if options.garment not in GARMENTS:
        raise InputError(f"--garment {options.garment!r}: choose one of {', '.join(GARMENTS)}")
    if options.texture not in TEXTURES:
        raise InputError(f"--texture {options.texture!r}: choose one of {', '.join(TEXTURES)}")
    if options.skeleton not in SKELETONS:
        raise InputError(f"--skeleton {options.skeleton!r}: choose one of {', '.join(SKELETONS)}")
    if options.skeleton == "root" and options.test_frames:
        raise InputError(
            f"--skeleton root --test-frames {options.test_frames}: a static subject holds one pose, so it has no "
            "novel-pose test frames; give --test-frames 0 and --holdout-frames N for test views"
        )


def resolved_config(options: SynthOptions) -> dict:
    """The JSON config that determines the capture's content (recorded in its manifest)."""
    return {
        "resolution": int(options.resolution),
        "train_frames": int(options.train_frames),
        "test_frames": int(options.test_frames),
        **({"holdout_frames": int(options.holdout_frames)} if options.holdout_frames else {}),
        "phenotype": parse_phenotype(options.phenotype),
        "garment": options.garment,
        "texture": options.texture,
        "seed": int(options.seed),
        "camera_distance_m": CAMERA_DISTANCE_M,
        "supersample": SUPERSAMPLE,
        "background": list(BACKGROUND),
        # Only when not the default, so that captures made before the option keep their config.
        **({"skeleton": options.skeleton} if options.skeleton != "anny" else {}),
    }


@dataclass(frozen=True)
class SequencePart:
    """Frames made by one motion: names, split, the motion, its seed and its yaw about the vertical."""

    motion: Motion
    split: str
    frames: tuple[str, ...]
    seed: int
    yaw: float


def make_sequence(
    body: AnnyBody, train_frames: int, test_frames: int, seed: int, holdout_frames: int = 0, static: bool = False
) -> list[SequencePart]:
    """The training turn, the hold-out turn (if any), then the test motions (split as evenly as possible).

    `static` holds the body still in the A-pose while it turns (no small motion in either turn).
    """
    skeleton = body.skeleton
    parts = [
        SequencePart(
            motion=turntable("anny", train_frames, seed, small_motion=not static, fps=TRAIN_FPS, skeleton=skeleton),
            split="train",
            frames=tuple(f"train_{i:04d}" for i in range(train_frames)),
            seed=seed,
            yaw=0.0,
        )
    ]
    if holdout_frames:
        # Another seed gives other small motions; the yaw puts its views half-way between the
        # training turn's (which steps 2 pi / train_frames per frame).
        parts.append(SequencePart(
            motion=turntable("anny", holdout_frames, seed + 100, small_motion=not static, fps=TRAIN_FPS, skeleton=skeleton),
            split="test", frames=tuple(f"test_holdout_{i:04d}" for i in range(holdout_frames)),
            seed=seed + 100, yaw=float(np.pi / train_frames),
        ))
    rng = np.random.default_rng([seed, 1])
    counts = [test_frames // len(TEST_MOTIONS) + (k < test_frames % len(TEST_MOTIONS)) for k in range(len(TEST_MOTIONS))]
    for k, ((name, seconds, (yaw_low, yaw_high)), count) in enumerate(zip(TEST_MOTIONS, counts)):
        yaw = float(rng.uniform(yaw_low, yaw_high) * rng.choice([-1.0, 1.0]))
        if count == 0:
            continue
        fps, motion_seed = count / seconds, seed + 1 + k
        if name == "walk":
            # In place, so that the static camera keeps the subject as large as in the other frames.
            motion = walk("anny", count, motion_seed, fps=fps, in_place=True, skeleton=skeleton)
        else:
            motion = motion_by_name(name, "anny", count, motion_seed, fps=fps, skeleton=skeleton)
        frames = tuple(f"test_{name}_{i:04d}" for i in range(count))
        parts.append(SequencePart(motion, "test", frames, motion_seed, yaw))
    return parts


def sequence_poses(body: AnnyBody, parts: list[SequencePart]) -> tuple[torch.Tensor, torch.Tensor]:
    """Local rotations (N, J, 3, 3) and root translations (N, 3), float64, of all parts in order."""
    rotations, translations = [], []
    for part in parts:
        r = part.motion.local_rotations_for(body.skeleton, dtype=torch.float64)
        t = part.motion.root_translation_tensor(dtype=torch.float64)
        if part.yaw != 0.0:
            r, t = yaw_about_vertical(r, t, part.yaw)
        rotations.append(r)
        translations.append(t)
    return torch.cat(rotations), torch.cat(translations)


def pose_subject(
    subject: ClothedSubject, body: AnnyBody, local_rotations: torch.Tensor, root_translation: torch.Tensor, chunk: int = 16
) -> np.ndarray:
    """(N, V, 3) float64 world positions of the clothed surface: igavatar FK + LBS with the body's bones.

    Canonical = Anny's rest pose, so each bone's transform is G_j(pose) @ [I | -rest_j].
    """
    rest_joints = torch.tensor(np.array(body.skeleton.rest_joints), dtype=torch.float64)
    x_canonical = torch.as_tensor(subject.vertices_canonical, dtype=torch.float64)
    weights = torch.as_tensor(subject.weights, dtype=torch.float64)
    to_rest = rigid_matrix(torch.eye(3, dtype=torch.float64), -rest_joints)
    out = []
    for start in range(0, local_rotations.shape[0], chunk):
        global_posed = forward_kinematics(
            local_rotations[start : start + chunk], rest_joints, body.skeleton.parents, root_translation[start : start + chunk]
        )
        out.append(linear_blend_skinning(x_canonical, weights, global_posed @ to_rest).numpy())
    return np.concatenate(out)


def build_subject(body: AnnyBody, garment: str) -> ClothedSubject:
    """The clothed surface of `body` (see igavatar.synth.garments.build_clothed_subject)."""
    return build_clothed_subject(
        body.rest_vertices.numpy().astype(np.float64),
        body.faces.numpy(),
        body.skinning_weights.numpy(),
        body.skeleton.joint_names,
        body.skeleton.rest_joints,
        garment,
    )


def build_texture(body: AnnyBody, style: str, seed: int) -> SolidTexture:
    """The subject's solid texture, anchored on the body's face and chest."""
    landmarks = find_landmarks(
        body.rest_vertices.numpy().astype(np.float64),
        body.skinning_weights.numpy(),
        body.skeleton.joint_names,
        np.asarray(body.skeleton.rest_joints),
    )
    return make_texture(style, seed, landmarks)


def _shader(subject: ClothedSubject, texture: SolidTexture, normals_world: np.ndarray, light: np.ndarray):
    """shade(hits, x_world, view_dirs): textured albedo at the canonical hit point, Lambert-lit."""

    # One gather for all per-vertex attributes: canonical position, coverage, posed normal.
    attributes = np.concatenate([subject.vertices_canonical, subject.coverage, normals_world], axis=1)
    channels = np.cumsum([0, 3, subject.coverage.shape[1], 3])

    def shade(hits: RayHits, x_world: np.ndarray, view_dirs: np.ndarray) -> np.ndarray:
        values = interpolate_vertex_values(attributes, subject.faces, hits)
        x_canonical, coverage, normals = (values[:, a:b] for a, b in zip(channels[:-1], channels[1:]))
        normals = normals / np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
        albedo = texture.albedo(x_canonical, region_ids(coverage))
        return lambert_shading(albedo, normals, x_world, light)

    return shade


#: The clothed surface in the body model's rest pose with its skinning weights (ground truth of
#: the canonical shape: `eval` poses it into the dataset's canonical pose).
REST_SURFACE = REST_SURFACE_FILE
REST_SURFACE_INFLUENCES = 8


def _write_rest_surface(path: Path, subject: ClothedSubject) -> None:
    """vertices (V, 3), faces (F, 3), top-k joint indices and renormalized weights (V, k)."""
    weights = np.asarray(subject.weights, np.float32)
    top = np.argsort(-weights, axis=1)[:, :REST_SURFACE_INFLUENCES]
    value = np.take_along_axis(weights, top, axis=1)
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez(path, vertices=subject.vertices_canonical.astype(np.float64), faces=subject.faces.astype(np.int64),
             weights_index=top.astype(np.int64), weights_value=value / value.sum(axis=1, keepdims=True))


def _capture_poses(options: SynthOptions, body: AnnyBody, local_rotations: torch.Tensor, root_translation: torch.Tensor,
                   x_posed: np.ndarray) -> dict[str, np.ndarray]:
    """poses.npz of the chosen skeleton: Anny's pose parameters, bare joints, or one rigid root."""
    if options.skeleton == "anny":
        return {
            "pose_parameters": body.pose_parameters_from_local_rotations(local_rotations, root_translation).numpy(),
            "phenotype_labels": np.array(body.phenotype_labels, dtype=np.str_),
            "phenotype_values": body.phenotype_values,
        }
    if options.skeleton == "bare":
        return bare_skeleton_poses(body.skeleton, local_rotations, root_translation)
    return root_only_poses(x_posed)


def _capture_meta(options: SynthOptions, config: dict, parts: list, subject: ClothedSubject, printed_text: str) -> dict:
    """capture.json (also the manifest's data)."""
    return {
        "format": "igavatar-capture",
        "version": 1,
        "body_model": "anny" if options.skeleton == "anny" else "skeleton",
        "frames": [name for part in parts for name in part.frames],
        "splits": {
            "train": [f for p in parts if p.split == "train" for f in p.frames],
            "test": [f for p in parts if p.split == "test" for f in p.frames],
        },
        "fps": TRAIN_FPS,
        "image_ext": ".png",
        "subject": {
            "phenotype": config["phenotype"],
            "garment": options.garment,
            "texture": options.texture,
            "printed_text": printed_text,
            "seed": int(options.seed),
            "vertices": int(subject.vertices_canonical.shape[0]),
            "faces": int(subject.faces.shape[0]),
        },
        "motions": {
            part.motion.name: {"split": part.split, "frames": list(part.frames), "fps": part.motion.fps,
                               "yaw_rad": part.yaw, "seed": part.seed}
            for part in parts
        },
        "camera": {"distance_m": CAMERA_DISTANCE_M, "static": True, "supersample": SUPERSAMPLE},
    }


def _render_frames(tmp: Path, frames: list[str], x_posed: np.ndarray, subject: ClothedSubject, texture, rays: CameraRays,
                   light: np.ndarray, progress: ProgressSink) -> None:
    """images/, masks/ and scans/ of every frame (ray cast, supersampled)."""
    for sub in ("images", "masks", "scans"):
        (tmp / sub).mkdir()
    with progress.task("rendering frames", total=len(frames)) as advance:
        for index, name in enumerate(frames):
            x_world = x_posed[index]
            caster = MeshRayCaster(x_world, subject.faces)
            normals = vertex_normals(x_world, subject.faces)
            frame = render_mesh(caster, rays, _shader(subject, texture, normals, light), background=BACKGROUND)
            write_png(tmp / "images" / f"{name}.png", frame.rgb)
            write_png(tmp / "masks" / f"{name}.png", frame.mask.astype(bool))
            trimesh.Trimesh(x_world, subject.faces, process=False).export(tmp / "scans" / f"{name}.ply")
            advance(1)


def run_synth(options: SynthOptions, progress: ProgressSink = NULL_PROGRESS) -> dict:
    """Write a capture v1 of a clothed, textured Anny subject to `options.out`; return a summary.

    Skips (and says so) when `out` already holds a valid capture with the same config, unless
    `options.force`. Raises InputError for bad options, BodyModelError if Anny cannot be loaded.
    """
    _check_options(options)
    config = resolved_config(options)
    out = Path(options.out)
    if not options.force and unchanged(out, "capture", config, []):  # read-only, so before the target check
        # The one summary whose "skipped" is a flag: a synth run always says whether it rendered.
        return {"path": str(out), "skipped": True, "reason": "a capture with the same config exists (use --force to redo)"}
    check_output_target(out, "capture")
    clock = StageClock()
    with clock("subject_s"):
        body = AnnyBody(load_anny(options.anny_cache, on_status=progress.status), config["phenotype"])
        subject = build_subject(body, options.garment)
        texture = build_texture(body, options.texture, options.seed)
    parts = make_sequence(body, options.train_frames, options.test_frames, options.seed, options.holdout_frames,
                          static=options.skeleton == "root")
    meta = _capture_meta(options, config, parts, subject, texture.text)
    local_rotations, root_translation = sequence_poses(body, parts)
    x_posed = pose_subject(subject, body, local_rotations, root_translation)
    size = int(options.resolution)
    K, w2c = frame_static_camera(x_posed.reshape(-1, 3), size, size, distance=CAMERA_DISTANCE_M)
    rays = CameraRays(K, w2c, size, size, supersample=SUPERSAMPLE)
    with atomic_directory(out, kind="capture") as tmp:
        with clock("render_s"):
            _render_frames(tmp, meta["frames"], x_posed, subject, texture, rays, light_position(w2c), progress)
            np.savez(tmp / "cameras.npz", K=K, w2c=w2c, height=np.int64(size), width=np.int64(size))
            np.savez(tmp / "poses.npz", **_capture_poses(options, body, local_rotations, root_translation, x_posed))
            _write_rest_surface(tmp / REST_SURFACE, subject)
            (tmp / "capture.json").write_text(json.dumps(meta, indent=2) + "\n")
        build_manifest(
            "capture", tmp, stage="synth", config=config, inputs=[], data=meta, seed=int(options.seed),
            timings=clock.finish(), peak_memory={"ram_bytes": float(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss) * 1024.0},
        )
    n_frames = len(meta["frames"])
    return {
        "path": str(out), "skipped": False, "frames": n_frames,
        "train_frames": len(meta["splits"]["train"]), "test_frames": len(meta["splits"]["test"]),
        "resolution": f"{size}x{size}", "garment": options.garment, "texture": options.texture,
        "seconds": round(clock.elapsed(), 2), "seconds_per_frame": round(clock.timings["render_s"] / n_frames, 3),
    }
