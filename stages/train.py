"""`igavatar train`: a dataset artifact -> a model artifact (the trained avatar).

    summary = run_train(TrainOptions(dataset=Path("run/dataset"), out=Path("run/model"), preset="cpu"))

TrainOptions and the TrainConfig they resolve to are stages.train_options.

Model layout (schema `model`, version 1):
    weights.npz          avatar parameters and buffers, canonical occupancy grid (no pickle)
    subject.npz          skeleton, skinning grid and boxes (copied from the dataset, or the prior voted
                         on the poses fitted to the masks: stages.train_prior)
    prior.ply            that prior's mesh, the masks' visual hull (only then)
    shape_init.npz       SDF weights after shape initialization (reused by later runs)
    training_log.csv     step, losses, PSNR, beta, samples, seconds
    validation/*.png     ground truth | render | normals of a training and a test frame

While training, checkpoints live in `<out>.work/` beside the artifact; `--resume` continues from
the last one exactly, and Ctrl-C writes one before exiting.
"""

from __future__ import annotations

import dataclasses
import json
import shutil
import time
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np
import torch

from igavatar.artifacts.atomic import atomic_directory
from igavatar.artifacts.storage import storage_errors
from igavatar.artifacts.targets import check_output_target
from igavatar.artifacts.manifest import InputRecord, build_manifest, sha256_file, sha256_json
from igavatar.artifacts.png import write_png
from igavatar.avatar.dataset import PRIOR_FILE, DatasetArtifact, read_dataset, training_data
from igavatar.avatar.model import build_avatar
from igavatar.avatar.subject import SUBJECT_FILE
from igavatar.errors import IgavatarError, InputError, Terminated
from igavatar.interrupts import deferred_interrupts, raise_if_interrupted
from igavatar.metrics.image import psnr as image_psnr
from igavatar.model.avatar import Avatar
from igavatar.training.checkpoint import save_state
from igavatar.training.config import TrainConfig
from igavatar.training.run_state import TrainingLog, cached_shape_init, checkpoint_of_this_run, fit_shape, shape_init_key
from igavatar.training.pose_refine import REFINED_POSES_FILE, PoseRefiner
from igavatar.training.pose_silhouette import SilhouetteFit, fit_poses_to_masks
from igavatar.training.trainer import Trainer
from igavatar.viewer.server import check_port_free
from stages.kernels import build_kernels, resolve_device
from stages.common import StageClock, skipped, unchanged
from stages.progress import NULL_PROGRESS, ProgressSink
from stages.resources import TRAIN_BYTES_PER_SAMPLE, peak_cuda_bytes, peak_ram_bytes, require_memory
from stages.train_options import TrainOptions, resolve_config, with_outline_px
from stages.train_prior import REVOTED_PRIOR_FILE, RevotedPrior, revote_prior

if TYPE_CHECKING:  # viser is imported only for --view
    from stages.train_view import TrainingMonitor


class TrainingInterrupted(IgavatarError):
    """Ctrl-C during training: a checkpoint was written; `--resume` continues from it."""

    exit_code = 130


def _pose_refiner(config: TrainConfig, dataset: DatasetArtifact, data) -> PoseRefiner | None:
    if not config.refine_poses:
        return None
    subject = dataset.subject
    # The root and the major bones (those root finding starts from): the ones the images see.
    joints = np.union1d([0], subject.init_bones)
    return PoseRefiner(data.bone_transforms, subject.parents, subject.rest_joints, subject.canonical_rotations,
                       data.train_indices, joints)


def _write_refined_poses(path: Path, trainer: Trainer) -> None:
    """refined_poses.npz: the training frames' corrected transforms, the corrected joints and the corrections."""
    refiner = trainer.pose_refiner
    names = np.array([trainer.data.frame_names[int(i)] for i in refiner.frames], dtype=np.str_)
    np.savez(path, frame_names=names, bone_transforms=refiner.all_bone_transforms().float().cpu().numpy(),
             joints=refiner.joints.cpu().numpy(), rotation_corrections=refiner.rotation.detach().cpu().numpy(),
             translation_corrections=refiner.translation.detach().cpu().numpy())


def _rounded(report: dict) -> dict:
    """A pose pass's summary for the manifest: floats to 5 decimals."""
    return {k: round(v, 5) if isinstance(v, float) else v for k, v in report.items()}


def config_to_json(config: TrainConfig) -> dict:
    return json.loads(json.dumps(dataclasses.asdict(config), default=str))


def _body_template(dataset: DatasetArtifact) -> tuple[np.ndarray, np.ndarray] | None:
    """The body model's naked template (vertices, faces), or None for a capture without one."""
    path = dataset.body_template_path
    if not path.is_file():
        return None
    import trimesh

    mesh = trimesh.load(path, process=False)
    return np.asarray(mesh.vertices), np.asarray(mesh.faces)


def _fit_poses_to_masks(config: TrainConfig, dataset: DatasetArtifact, data, avatar: Avatar, refiner: PoseRefiner | None,
                        resumed: dict | None, progress: ProgressSink) -> SilhouetteFit | None:
    """The training poses' fit to the masks (igavatar.training.pose_silhouette), before the trainer
    votes its priors on them: run now, or for a resumed run the one its checkpoint recorded. An
    interrupt undoes the whole fit, and no checkpoint exists yet."""
    if refiner is None or config.pose_silhouette_steps == 0:
        return None
    if resumed is not None:
        state = resumed["trainer"].get("pose_silhouette")
        if state is None:
            return None
        fit = SilhouetteFit.from_state(state)
        fit.apply(refiner)
        return fit
    import trimesh

    progress.status("fitting the training poses to the masks")
    prior_vertices = np.asarray(trimesh.load(dataset.path / PRIOR_FILE, process=False).vertices)
    return fit_poses_to_masks(refiner, data, avatar.deformer, prior_vertices, config)


def _shape_initialize(
    avatar: Avatar, config: TrainConfig, template: Path, canonical_box: np.ndarray, cache_paths: list[Path],
    progress: ProgressSink,
) -> tuple[dict, float, Path | None]:
    """Fit the SDF to the prior's mesh at `template` inside `canonical_box` (2, 3) (or reuse a cached
    fit); returns (sdf state, seconds, the cache reused or None)."""
    key = shape_init_key(config, sha256_file(template) if template.is_file() else None, canonical_box)
    cached, path = cached_shape_init(avatar, key, cache_paths)
    if cached is not None:
        progress.status(f"shape initialization reused from {path}")
        return cached, 0.0, path
    started = time.perf_counter()
    if not (template.is_file() and config.shape_init_steps > 0):
        progress.status("no template mesh: the SDF starts as a sphere")
        return fit_shape(avatar, config, template, canonical_box, key, on_step=None), 0.0, None
    with progress.task("shape initialization", total=config.shape_init_steps) as advance:
        state = fit_shape(avatar, config, template, canonical_box, key,
                          on_step=lambda step, loss: (raise_if_interrupted(), advance(1, loss=f"{loss:.4f}")))
    return state, time.perf_counter() - started, None


def _validation_png(trainer: Trainer, index: int, scale: float, samples: int) -> tuple[np.ndarray, float]:
    """ground truth | render | normal map side by side (uint8 RGB), and the render's PSNR on white."""
    render = trainer.render_frame(index, scale, samples)
    rgb = (render.rgb.clamp(0, 1).cpu().numpy() * 255).astype(np.uint8)
    h, w = rgb.shape[:2]
    gt = trainer.data.images[index].numpy()
    mask = trainer.data.masks[index].numpy()
    gt = np.where(mask[..., None], gt, 255).astype(np.uint8)
    gt = cv2.resize(gt, (w, h), interpolation=cv2.INTER_AREA)
    normal = render.normal.cpu().numpy()
    normal_rgb = ((normal * 0.5 + 0.5) * 255).clip(0, 255).astype(np.uint8)
    opacity = render.opacity.cpu().numpy()[..., None]
    normal_rgb = (normal_rgb * opacity + 255 * (1 - opacity)).astype(np.uint8)
    psnr = image_psnr(rgb.astype(np.float64) / 255.0, gt.astype(np.float64) / 255.0)
    return np.concatenate([gt, rgb, normal_rgb], axis=1), float(psnr)


def work_directory(out: Path) -> Path:
    """Where a run writing `out` keeps its checkpoints: `<out>.work/` beside it."""
    return out.with_name(out.name + ".work")


def run_train(options: TrainOptions, progress: ProgressSink = NULL_PROGRESS) -> dict:
    """Train an avatar on a dataset artifact and write the model artifact.

    Raises InputError/ArtifactError for bad inputs, StorageError when the disk refuses a write,
    and TrainingInterrupted on Ctrl-C or SIGTERM (after writing a checkpoint). A run that fails
    before any checkpoint exists leaves no `<out>.work/` behind (only a checkpoint is resumable).
    """
    work = work_directory(Path(options.out))
    checkpoint = work / "checkpoint.npz"
    if options.resume and not checkpoint.is_file():
        raise InputError(f"--resume: no checkpoint at {checkpoint}; start without --resume")
    existed = work.exists()
    try:
        with storage_errors(work):
            return _run_train(options, progress)
    except BaseException:
        if not existed and not checkpoint.is_file():
            shutil.rmtree(work, ignore_errors=True)
        raise


def _train_loop(trainer: Trainer, config: TrainConfig, log: TrainingLog, save_checkpoint, validation_frame: int,
                work: Path, progress: ProgressSink, monitor: TrainingMonitor | None = None) -> dict[str, float]:
    """Step until the end; checkpoint, log and validate on schedule. Ctrl-C/SIGTERM checkpoint and raise."""
    last: dict[str, float] = {}
    try:
        with progress.task("training", total=trainer.total_steps) as advance:
            advance(trainer.step)
            while trainer.step < trainer.total_steps:
                raise_if_interrupted()  # one a library swallowed (trimesh catches BaseException)
                if trainer.pose_align_due():
                    # Minutes long, so not deferred: an interrupt undoes the whole pass (pose_align).
                    progress.status(f"step {trainer.step}: fitting each training frame's pose to its image")
                    trainer.align_poses()
                # A step is whole or not at all: an interrupt inside it (after the optimizer, before
                # the step count) would checkpoint half a step, and --resume would not be exact.
                with deferred_interrupts():
                    last = trainer.train_step()
                    if trainer.step % config.log_every == 0 or trainer.step == trainer.total_steps:
                        log.rows.append({"step": trainer.step, **{k: f"{v:.6g}" for k, v in last.items()}})
                if config.checkpoint_every and trainer.step % config.checkpoint_every == 0:
                    save_checkpoint()
                if config.validate_every and trainer.step % config.validate_every == 0 and trainer.step < trainer.total_steps:
                    panel, _ = _validation_png(trainer, validation_frame, config.validation_scale, config.validation_samples)
                    write_png(work / "validation" / f"step_{trainer.step:06d}.png", panel)
                    if monitor is not None:
                        monitor.validation(trainer.step, panel)
                rate = trainer.step / max(trainer.seconds, 1e-9)
                if monitor is not None:
                    monitor.step(trainer, last, rate)
                advance(1, loss=f"{last['loss']:.4f}", psnr=f"{last['psnr']:.2f}", it_s=f"{rate:.2f}")
    except KeyboardInterrupt as exc:
        save_checkpoint()
        interrupted = TrainingInterrupted(
            f"training {'terminated (SIGTERM)' if isinstance(exc, Terminated) else 'interrupted'} at step {trainer.step}; "
            f"checkpoint saved to {log.path.parent / 'checkpoint.npz'} (continue with `igavatar train --resume` and the "
            "same options)"
        )
        interrupted.exit_code = 143 if isinstance(exc, Terminated) else 130  # the shell's 128 + signal number
        raise interrupted from None
    save_checkpoint()
    return last


def _model_data(dataset: DatasetArtifact, trainer: Trainer, last: dict[str, float], validation: dict,
                config: TrainConfig, revote: RevotedPrior | None) -> dict:
    """The model manifest's data: the dataset's facts it carries on, the run's outcome and speed."""
    data, train_seconds = dataset.data, trainer.seconds
    model_data = {
        "dataset": str(dataset.path),
        # The dataset's facts every later stage needs, carried over as the dataset recorded them.
        **{key: data[key] for key in ("body_model", "joint_names", "pose_dim", "image_size", "canonical_box", "splits")},
        "subject": data.get("subject", {}),
        "steps": trainer.step,
        "final": {k: last.get(k) for k in ("loss", "psnr", "rgb", "alpha", "eikonal", "smooth", "beta") if k in last},
        "speed": {
            "iterations_per_second": trainer.step / max(train_seconds, 1e-9),
            "rays_per_second": trainer.rays_seen / max(train_seconds, 1e-9),
            "samples_per_second": trainer.samples_seen / max(train_seconds, 1e-9),
            "threads": torch.get_num_threads(),
        },
        "validation_frames": list(validation),
        "validation_psnr": {name: psnr for name, (_, psnr) in validation.items()},
        "validation_scale": config.validation_scale,
        **({"body_inside": trainer.body_inside_check} if trainer.body_inside_check is not None else {}),
        **({"pose_refinement": {"frames": len(trainer.pose_refiner.frames), "file": REFINED_POSES_FILE,
                                **{k: round(v, 4) for k, v in trainer.pose_refiner.correction_magnitudes().items()},
                                "silhouette": None if trainer.pose_silhouette is None else
                                _rounded(trainer.pose_silhouette.report),
                                "passes": [_rounded(report) for report in trainer.pose_align_reports],
                                "prior_vote": None if revote is None else _rounded(revote.report)}}
           if trainer.pose_refiner is not None else {}),
    }
    if revote is not None and revote.subject is not None:
        model_data["canonical_box"] = revote.subject.canonical_box.tolist()  # the hull's, not the dataset's
    return model_data


def _write_model_files(tmp: Path, dataset: DatasetArtifact, trainer: Trainer, shape_state: dict, log: TrainingLog,
                       validation: dict, revote: RevotedPrior | None) -> None:
    """weights.npz, subject.npz (the dataset's, or the prior voted on the fitted poses with its mesh
    prior.ply), shape_init.npz, training_log.csv and validation/*.png."""
    save_state(tmp / "weights.npz", {"avatar": trainer.avatar.state_dict(), "canonical_grid": trainer.canonical_grid.state_dict()})
    if revote is not None and revote.subject is not None:
        revote.subject.write(tmp / SUBJECT_FILE)
        shutil.copyfile(revote.mesh_path, tmp / REVOTED_PRIOR_FILE)
    else:
        shutil.copyfile(dataset.path / SUBJECT_FILE, tmp / SUBJECT_FILE)
    save_state(tmp / "shape_init.npz", shape_state)
    shutil.copyfile(log.path, tmp / "training_log.csv")
    if trainer.pose_refiner is not None:
        _write_refined_poses(tmp / REFINED_POSES_FILE, trainer)
    for name, (image, _) in validation.items():
        write_png(tmp / "validation" / f"{name}.png", image)


def _run_train(options: TrainOptions, progress: ProgressSink) -> dict:
    clock = StageClock()
    dataset = read_dataset(Path(options.dataset))
    out = Path(options.out)
    config = with_outline_px(resolve_config(options), dataset.image_size)
    # Read-only, so before the target check; a --resume always continues its checkpoint.
    if not (options.force or options.resume) and unchanged(out, "model", config_to_json(config),
                                                           [InputRecord(dataset.path, "dataset")]):
        return skipped("model", out)
    check_output_target(out, "model", [dataset.path])  # before minutes of training, not after
    if options.view is not None:  # a busy port fails now, not after the shape initialization
        check_port_free(options.view.host, options.view.port, "--view-port")
    device = resolve_device(options.device)
    build_kernels(device, progress)
    require_memory(config.rays_per_step * config.samples_per_ray * TRAIN_BYTES_PER_SAMPLE,
                   f"--rays {config.rays_per_step} x --samples {config.samples_per_ray} (one training step)", device)
    torch.manual_seed(config.seed)
    data = training_data(dataset)
    avatar = build_avatar(config, dataset.subject, dataset.pose_dim)

    work = work_directory(out)
    work.mkdir(parents=True, exist_ok=True)
    checkpoint = work / "checkpoint.npz"
    config_json = config_to_json(config)
    dataset_sha = sha256_file(dataset.path / "manifest.json")
    run_key = sha256_json({"config": config_json, "dataset": dataset_sha})
    # Refused before anything in the work folder is touched.
    resumed = checkpoint_of_this_run(checkpoint, run_key, config_json, dataset_sha) if options.resume else None
    # The poses' fit to the masks and the prior's vote on them come first: the SDF starts from that prior.
    refiner = _pose_refiner(config, dataset, data)
    silhouette = _fit_poses_to_masks(config, dataset, data, avatar, refiner, resumed, progress)
    revote = revote_prior(config, dataset, data, refiner, silhouette, work, progress)
    subject, prior_mesh = dataset.subject, dataset.path / PRIOR_FILE
    if revote is not None and revote.subject is not None:
        progress.status(f"the shape prior is now the masks' visual hull (loose {revote.report['loose']:.3f}, spill "
                        f"{revote.report['spill']:.3f} on the fitted poses)")
        subject, prior_mesh, data = revote.subject, revote.mesh_path, revote.with_boxes(data)
        torch.manual_seed(config.seed)  # the same start as an avatar built on this prior from the first
        avatar = build_avatar(config, subject, dataset.pose_dim)
    shape_state, shape_seconds, reused_from = _shape_initialize(
        avatar, config, prior_mesh, subject.canonical_box, [work / "shape_init.npz", out / "shape_init.npz"], progress
    )
    clock.add("shape_init_s", shape_seconds)
    if reused_from != work / "shape_init.npz":
        save_state(work / "shape_init.npz", shape_state)
    # The template is read only when the body-inside term will use it.
    body_template = _body_template(dataset) if config.loss_weights.body_inside > 0 else None
    trainer = Trainer(config, data, avatar, device, body_template=body_template, pose_refiner=refiner,
                      pose_silhouette=silhouette)
    _say_why_body_inside_is_off(trainer.body_inside_check, progress)
    if resumed is not None:
        trainer.load_state_dict(resumed["trainer"])
        progress.status(f"resumed from step {trainer.step} of {trainer.total_steps}")
    log = TrainingLog.open(work / "training_log.csv", options.resume)

    def save_checkpoint() -> None:
        with deferred_interrupts():  # the checkpoint and its log rows are written together
            save_state(checkpoint, {"run_key": run_key, "config": json.dumps(config_json),
                                    "dataset_sha256": dataset_sha, "trainer": trainer.state_dict()})
            log.save()

    # The first training frame and, when there is one, the first test frame.
    test_frames = [i for i, name in enumerate(data.frame_names) if name in dataset.splits.get("test", [])]
    validation_frames = [int(data.train_indices[0]), *test_frames[:1]]
    monitor = None
    if options.view is not None:
        from stages.train_view import TrainingMonitor

        monitor = TrainingMonitor.open(options.view, dataset, trainer.total_steps, progress)
    try:
        last = _train_loop(trainer, config, log, save_checkpoint, validation_frames[0], work, progress, monitor)
        clock.add("train_s", trainer.seconds)
        with clock("validation_render_s"):
            validation = {data.frame_names[i]: _validation_png(trainer, i, config.validation_scale, config.validation_samples)
                          for i in validation_frames}
        if monitor is not None:
            monitor.validation(trainer.step, next(iter(validation.values()))[0])
    finally:
        view_cost = None if monitor is None else monitor.close(f"stopped at step {trainer.step} of {trainer.total_steps}")
    data_json = _model_data(dataset, trainer, last, validation, config, revote)
    with atomic_directory(out, kind="model", inputs=[dataset.path]) as tmp:
        _write_model_files(tmp, dataset, trainer, shape_state, log, validation, revote)
        build_manifest(
            "model", tmp, stage="train", config=config_json, inputs=[InputRecord(dataset.path, "dataset")],
            data=data_json, seed=config.seed, device=str(device), timings=clock.finish(),
            peak_memory={"ram_bytes": peak_ram_bytes(), "cuda_bytes": peak_cuda_bytes()},
        )
    shutil.rmtree(work, ignore_errors=True)
    return {**_summary(out, trainer, device, data_json, validation), **({"viewer": view_cost} if view_cost else {})}


def _say_why_body_inside_is_off(check: dict | None, progress: ProgressSink) -> None:
    """A status line when the body-inside term was measured and not used (None: not asked for)."""
    if check is None or check["used"]:
        return
    progress.status(
        "body-inside term off: " + ("the masks confirm no point of the body model's template" if not check["kept"] else
        f"the body model's template spills past the masks (spill {check['spill']:.3f} > {check['max_spill']}: "
        "the fit looks heavier than the subject, or the masks are tight; a fitted template with exact masks stays "
        "under 0.02; --body-inside-max-spill 1 uses it anyway)")
    )


def _summary(out: Path, trainer: Trainer, device: torch.device, data_json: dict, validation: dict) -> dict:
    return {
        "model": str(out), "steps": trainer.step, "device": str(device),
        "train_seconds": round(trainer.seconds, 1),
        "it_per_s": round(data_json["speed"]["iterations_per_second"], 2),
        "samples_per_s": round(data_json["speed"]["samples_per_second"]),
        "validation_psnr": {name: round(psnr, 2) for name, (_, psnr) in validation.items()},
        "validation": [str(out / "validation" / f"{n}.png") for n in validation],
        "peak_ram_gb": round(peak_ram_bytes() / 2**30, 2),
    }
