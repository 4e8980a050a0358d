"""One training run of the avatar: sampling, rendering, losses, schedule, occupancy, validation.

    trainer = Trainer(config, data, avatar, device="cpu")
    while trainer.step < trainer.total_steps:
        log = trainer.train_step()          # {"loss": ..., "rgb": ..., "psnr": ...}

Each step takes one training frame, draws ray patches mostly on the subject, skips empty space
with the frame's posed occupancy grid, maps the remaining samples to canonical space (Fast-SNARF
root finding + non-rigid offset), renders them on random-noise background and minimises
10 L_rgb + 0.1 L_alpha + 0.1 L_eik + 1.0 L_smooth (or an ablation's regularizer). All state that
decides the next step (weights, Adam moments, RNG, occupancy, step) is in `state_dict()`, so a
resumed run continues exactly.
"""

from __future__ import annotations

import math
import time
from collections import OrderedDict

import numpy as np
import torch

from igavatar.model.avatar import Avatar
from igavatar.model.deformer import PreparedFrame
from igavatar.model.fd_losses import curvature_loss, finite_difference_eikonal, finite_difference_terms
from igavatar.model.losses import (
    alpha_loss,
    eikonal_loss,
    linear_warmup,
    rgb_loss,
    smooth_loss_along_ray,
    smooth_loss_neighbour_rays,
    total_loss,
)
from igavatar.model.posed import PosedAvatar
from igavatar.model.render_avatar import render_avatar_view
from igavatar.render.occupancy import OccupancyGrid
from igavatar.render.rays import pixel_rays, rays_in_box
from igavatar.render.sampler import RaySamples, sample_along_rays
from igavatar.render.volume import ImageRender, render_rays
from igavatar.training.config import TrainConfig
from igavatar.training.data import TrainingData, sample_patch_pixels
from igavatar.training.optim import SparseAdam, adam
from igavatar.training.outline import outline_rays, texture_edge_rays, weights_gradient_scale
from igavatar.training.error_map import ErrorMap
from igavatar.training.pose_align import align_training_poses, pass_steps
from igavatar.training.pose_refine import PoseRefiner, with_pose_gradient
from igavatar.training.pose_silhouette import SilhouetteFit, corrected_data
from igavatar.training.body_prior import BodyInsidePoints, body_inside_loss, body_inside_points
from igavatar.training.visual_hull import (
    CanonicalHull, canonical_visual_hull, free_space_loss, training_skin, voting_views,
)

#: Prepared frames kept in memory (each is a (12, D, H, W) blended-transform grid).
PREPARED_CACHE = 512


def psnr_from_mse(mse: float) -> float:
    return -10.0 * math.log10(max(mse, 1e-12))


class Trainer:
    """Optimizes an Avatar on TrainingData following a TrainConfig.

    Args:
        config: the resolved TrainConfig.
        data: frames (CPU tensors; moved to `device` per step).
        avatar: the model (moved to `device`).
        device: torch device.
    """

    def __init__(
        self, config: TrainConfig, data: TrainingData, avatar: Avatar, device: torch.device | str = "cpu",
        body_template: tuple[np.ndarray, np.ndarray] | None = None, pose_refiner: PoseRefiner | None = None,
        pose_silhouette: SilhouetteFit | None = None,
    ):
        self.config = config
        self.data = data
        self.device = torch.device(device)
        self.avatar = avatar.to(self.device)
        self.total_steps = config.resolved_steps(len(data.train_indices))
        self.step = 0
        self.generator = torch.Generator(device="cpu").manual_seed(config.seed)
        box = avatar.canonical_box
        self.canonical_grid = OccupancyGrid(box[0], box[1], resolution=config.occupancy_resolution).to(self.device)
        tables = ("sdf_field.encoding.", "color_field.encoding.")
        table = [p for n, p in avatar.named_parameters() if n.startswith(tables)]
        beta = [p for n, p in avatar.named_parameters() if n.startswith("density.")]
        networks = [p for n, p in avatar.named_parameters() if not n.startswith((*tables, "density."))]
        self._base_lrs = [config.lr * config.table_lr_factor, config.lr * config.network_lr_factor, config.lr * config.beta_lr_factor]
        groups = [{"params": group, "lr": lr} for group, lr in zip((table, networks, beta), self._base_lrs)]
        # The table's entries are reached only where samples fall; tiny-cuda-nn's Adam leaves the
        # others alone, torch's moves them on their momentum (optim.SparseAdam says why that matters).
        self.table_optimizer: SparseAdam | None = None
        if config.table_adam == "sparse":
            self.table_optimizer = SparseAdam(groups[:1], betas=(0.9, 0.99), eps=config.adam_eps)
            groups = groups[1:]
        self.optimizer = adam(groups, betas=(0.9, 0.99), eps=config.adam_eps)
        # Each frame's corrections get a gradient only on the steps that draw that frame: the
        # sparse rule leaves the others where they are instead of drifting on momentum.
        self.pose_refiner = None if pose_refiner is None else pose_refiner.to(self.device)
        self.pose_optimizer = None if pose_refiner is None else SparseAdam(
            self.pose_refiner.parameters(), lr=config.pose_lr, betas=(0.9, 0.99), eps=1e-8)
        # The whole-frame pose passes done (pose_align), at the steps pose_align_steps_at() names.
        self.pose_align_reports: list[dict] = []
        # The poses' fit to the masks before the first step (pose_silhouette), when it ran: the
        # refiner holds its corrections now, and the body-inside prior is voted on them.
        self.pose_silhouette = pose_silhouette
        self._prepared: OrderedDict[int, PreparedFrame] = OrderedDict()
        self.error_map = None if config.error_sampling <= 0 else ErrorMap(
            int(data.images.shape[0]), data.image_size, config.error_cell_px)
        self.hull: CanonicalHull | None = None
        self._hull_cells_cache: torch.Tensor | None = None
        if config.loss_weights.free_space > 0 or config.hull_in_occupancy:
            self.hull = canonical_visual_hull(self.avatar.deformer, data, box, cell_size=config.hull_cell_size)
        self.body_inside: BodyInsidePoints | None = None
        self.body_inside_check: dict | None = None
        if config.loss_weights.body_inside > 0 and body_template is not None:
            # With corrections (a fit to the masks), the template is voted in the poses they make.
            voting = data if pose_silhouette is None else corrected_data(data, self.pose_refiner)
            body = body_inside_points(*body_template, training_skin(self.avatar.deformer, voting), voting_views(voting),
                                      seed=config.seed)
            # No confirmed point, or a template that spills past fine masks (a fit too heavy): no term.
            used = body.trusted(config.body_inside_max_spill)
            self.body_inside_check = {
                "sampled": body.sampled, "kept": len(body.points), "spill": body.spill if len(body.points) else None,
                "max_spill": config.body_inside_max_spill, "pixel_m": body.pixel_m if len(body.points) else None,
                "spill_checked": body.spill_checked, "used": used,
            }
            self.body_inside = body if used else None
        self._patches_per_step = max(1, config.rays_per_step // config.patch_size**2)
        self.seconds = 0.0
        self.samples_seen = 0
        self.rays_seen = 0

    # ------------------------------------------------------------------ schedule
    def learning_rate_factor(self, step: int) -> float:
        """Linear warm-up, then polynomial decay (1 - step/steps)^power (official schedule)."""
        decay = max(0.0, 1.0 - step / max(1, self.total_steps)) ** self.config.lr_decay_power
        warmup = self.config.lr_warmup_steps
        if step < warmup:
            decay *= 0.01 + 0.99 * step / warmup
        return decay

    def beta_ceiling(self, step: int) -> float:
        """The cap on beta at `step`: geometric from beta_init to beta_final, then constant."""
        start, end = self.config.avatar.density.beta_init, float(self.config.beta_final)
        anneal = max(1, int(self.config.beta_anneal_fraction * self.total_steps))
        return start * (end / start) ** min(1.0, step / anneal)

    def pose_learning_rate(self, step: int) -> float:
        """The pose corrections' rate at `step`: pose_lr from the refinement's start, falling linearly
        to 0 at the end. A constant rate kept the corrections walking (Adam moves each entry by about
        the rate on every visit, however noisy its gradient) after the avatar's own rate had decayed,
        so the final poses fitted the final avatar worse than the estimates did
        (tests/benchmarks/results/zju377-registration.md)."""
        start = int(self.config.pose_refine_start_fraction * self.total_steps)
        left = max(1, self.total_steps - start)
        return self.config.pose_lr * min(1.0, max(0.0, (self.total_steps - step) / left))

    def pose_align_steps_at(self) -> list[int]:
        """The steps before which a whole-frame pose pass runs (none without pose refinement)."""
        return [] if self.pose_refiner is None else pass_steps(self.config, self.total_steps)

    def pose_align_due(self) -> bool:
        """Whether the next pose pass is due before the next step."""
        at = self.pose_align_steps_at()
        done = len(self.pose_align_reports)
        return done < len(at) and self.step >= at[done]

    def align_poses(self) -> dict:
        """Run the due whole-frame pose pass (igavatar.training.pose_align); returns its summary
        (kept in pose_align_reports). All or nothing: interrupted, it leaves the corrections and
        the passes done as they were. Its time is not a step's (`seconds` counts steps only)."""
        report = align_training_poses(self.avatar, self.canonical_grid, self.pose_refiner, self.data, self.config,
                                      seed=self.config.seed * 7 + len(self.pose_align_reports))
        report = {"step": self.step, **report}
        self.pose_align_reports.append(report)
        return report

    def _apply_schedule(self) -> None:
        factor = self.learning_rate_factor(self.step)
        for group, base in zip(self.param_groups(), self._base_lrs):
            group["lr"] = base * factor
        if self.pose_optimizer is not None:
            for group in self.pose_optimizer.param_groups:
                group["lr"] = self.pose_learning_rate(self.step)
        start = int(self.config.nonrigid_start_fraction * self.total_steps)
        window = max(1, int(self.config.nonrigid_window_fraction * self.total_steps))
        self.avatar.nonrigid.set_enabled(self.step >= start)
        self.avatar.nonrigid.set_window(min(1.0, max(0.0, (self.step - start) / window)))
        if self.config.beta_final is not None:
            self.avatar.density.set_ceiling(self.beta_ceiling(self.step))
        if self.config.regularizer == "hybrid-pe":
            anneal = max(1, int(self.config.hybrid_pe_anneal_fraction * self.total_steps))
            self.avatar.sdf_field.set_level_weights(self.step / anneal)

    def param_groups(self) -> list[dict]:
        """The table's, the networks' and beta's parameter groups, in that order."""
        table = self.table_optimizer.param_groups if self.table_optimizer is not None else []
        return table + self.optimizer.param_groups

    def frame_transforms(self, index: int) -> torch.Tensor:
        """(J, 4, 4) bone transforms of dataset frame `index`: refined when the frame is (with grad)."""
        if self.pose_refiner is not None and self.pose_refiner.refines(index):
            return self.pose_refiner.bone_transforms(index)
        return self.data.bone_transforms[index].to(self.device)

    def prepared_frame(self, index: int) -> PreparedFrame:
        """The deformer's per-frame precomputation, cached (the skinning grid is fixed) unless the
        frame's pose is being refined (then made anew, differentiable in the corrections)."""
        if self.pose_refiner is not None and self.pose_refiner.refines(index):
            return self.avatar.deformer.prepare(self.frame_transforms(index))
        if index in self._prepared:
            self._prepared.move_to_end(index)
            return self._prepared[index]
        frame = self.avatar.deformer.prepare(self.data.bone_transforms[index].to(self.device))
        self._prepared[index] = frame
        if len(self._prepared) > PREPARED_CACHE:
            self._prepared.popitem(last=False)
        return frame

    # ------------------------------------------------------------------ one step
    def _update_occupancy(self) -> None:
        grid_generator = torch.Generator(device=self.device).manual_seed(self.config.seed * 7919 + self.step)
        self.avatar.eval()
        self.canonical_grid.update(self.avatar.canonical_density, generator=grid_generator)
        if self.hull is not None and self.config.hull_in_occupancy:
            self.canonical_grid.occupied |= self._hull_cells()

    def _hull_cells(self) -> torch.Tensor:
        """(R, R, R) bool: occupancy cells whose center the visual hull keeps (computed once)."""
        if self._hull_cells_cache is None:
            centers = self.canonical_grid.cell_centers().reshape(-1, 3)
            kept = self.hull.free_distance(centers.cpu()) <= 0
            self._hull_cells_cache = kept.reshape(self.canonical_grid.occupied.shape).to(self.device)
        return self._hull_cells_cache

    def _body_inside_term(self) -> torch.Tensor:
        """The body-inside hinge on `body_inside_points` points drawn from the confirmed set."""
        body = self.body_inside
        pick = torch.randint(0, body.points.shape[0], (self.config.body_inside_points,), generator=self.generator)
        sdf, _ = self.avatar.sdf_field(body.points[pick].to(self.device))
        return body_inside_loss(sdf, body.template_sdf[pick].to(self.device), self.config.body_inside_slack)

    def _free_space_term(self) -> torch.Tensor:
        """The visual hull's free-space hinge on points drawn uniformly in the canonical box."""
        box = self.avatar.canonical_box
        u = torch.rand((self.config.free_space_points, 3), generator=self.generator).to(self.device)
        x = box[0] + u * (box[1] - box[0])
        bound = self.hull.free_distance(x)
        keep = bound > self.config.hull_cell_size
        sdf, _ = self.avatar.sdf_field(x[keep])
        return free_space_loss(sdf, bound[keep], slack=self.config.hull_cell_size)

    def _regularizer_terms(
        self, out, samples: RaySamples, x_rigid: torch.Tensor, pose_condition: torch.Tensor
    ) -> dict[str, torch.Tensor]:
        config = self.config
        valid = out.valid
        terms: dict[str, torch.Tensor] = {}
        reg = config.regularizer
        if reg in ("smooth", "none", "curvature", "hybrid-pe"):
            terms["eikonal"] = eikonal_loss(out.gradient[valid])
        if reg == "smooth" and config.smooth_pairs == "screen":
            # Rays are patch by patch, row-major (sample_patch_pixels); samples are not compacted,
            # so slot s is about the same depth on neighbouring rays.
            rays, slots = valid.shape
            edge = math.isqrt(rays // self._patches_per_step)
            shape = (self._patches_per_step, edge, edge, slots)
            terms["smooth"] = smooth_loss_neighbour_rays(out.gradient.reshape(*shape, 3), valid.reshape(shape))
        elif reg == "smooth":
            terms["smooth"] = smooth_loss_along_ray(
                out.gradient, valid, pairs=config.smooth_pairs, t_starts=samples.t_starts, t_ends=samples.t_ends,
                positions=samples.positions, sdf=out.sdf, band=config.smooth_band,
                normalization="released" if config.smooth_form == "released" else "samples",
            )
        if reg in ("fd-eikonal", "curvature", "fd-eikonal+curvature") and x_rigid.shape[0] > 0:
            x = self.avatar.offset_points(x_rigid, pose_condition)

            def sdf_fn(points: torch.Tensor) -> torch.Tensor:
                return self.avatar.sdf_field(points)[0]

            warm = linear_warmup(self.step, config.curvature_warmup_steps)
            if reg == "fd-eikonal":
                terms["fd_eikonal"] = finite_difference_eikonal(sdf_fn, x, config.fd_eps)
            elif reg == "curvature":
                terms["curvature"] = warm * curvature_loss(sdf_fn, x, config.fd_eps)
            else:
                fd_eik, curvature = finite_difference_terms(sdf_fn, x, config.fd_eps)
                terms["fd_eikonal"], terms["curvature"] = fd_eik, warm * curvature
        return terms

    def _draw_frame(self) -> int:
        """The step's training frame: uniform, or partly by the error map (config.error_sampling)."""
        frames = self.data.train_indices
        if self.error_map is not None:
            return self.error_map.draw_frame(frames, self.generator, self.config.error_sampling)
        return int(frames[torch.randint(0, len(frames), (1,), generator=self.generator)])

    def _weights_gradient_scale(self, index: int, pixels: torch.Tensor) -> float | torch.Tensor:
        """The colour loss's share through the compositing weights: one number, or (R,) per ray
        when the outline band is on (igavatar.training.outline)."""
        config = self.config
        if not config.color_shapes_geometry:
            return 0.0
        if config.color_weights_outline_px == 0:
            return config.color_weights_gradient
        if config.color_weights_outline_px < 0:
            raise ValueError("color_weights_outline_px is OUTLINE_AUTO: resolve it for the images first "
                             "(stages.train_options.with_outline_px)")
        width = config.color_weights_outline_px
        on_band = outline_rays(self.data.masks[index], pixels, width)
        on_edge = None
        if config.color_weights_edge_contrast > 0:
            on_edge = texture_edge_rays(self.data.images[index], self.data.masks[index], pixels, width,
                                        config.color_weights_edge_contrast)
        return weights_gradient_scale(on_band, config.color_weights_gradient, on_edge).to(self.device)

    def _draw_pixels(self, index: int) -> torch.Tensor:
        """The step's patch pixels (P, 2) of frame `index`; some person-centred patches centred on the
        mask's edge (config.outline_sampling) or steered by the error map (config.error_sampling)."""
        config = self.config
        mask_pixels = self.data.mask_pixels(index)
        n_in = int(round(self._patches_per_step * config.patch_centres_in_mask))
        chosen = []
        if config.outline_sampling > 0:
            chosen.append(self._outline_centres(index, int(round(n_in * config.outline_sampling))))
        if self.error_map is not None:
            n_steered = int(round(n_in * config.error_sampling))
            chosen.append(self.error_map.draw_centres(index, mask_pixels, n_steered, self.generator))
        steered = torch.cat(chosen) if chosen else None
        return sample_patch_pixels(mask_pixels, self.data.image_size, self._patches_per_step, config.patch_size,
                                   config.patch_centres_in_mask, self.generator, steered)

    def _outline_centres(self, index: int, count: int) -> torch.Tensor:
        """(count, 2) long: patch centres drawn uniformly from frame `index`'s mask edge."""
        edge = self.data.edge_pixels(index)
        return edge[torch.randint(0, edge.shape[0], (count,), generator=self.generator)]

    def train_step(self) -> dict[str, float]:
        """One optimization step; returns the step's scalar logs."""
        started = time.perf_counter()
        config, data, device = self.config, self.data, self.device
        if self.step % config.occupancy_update_every == 0:
            self._update_occupancy()
        self.avatar.train()
        self._apply_schedule()

        index = self._draw_frame()
        posed = PosedAvatar(self.avatar, self.prepared_frame(index), data.pose_condition[index].to(device))
        posed_box = data.posed_boxes[index].to(device)
        posed_grid = posed.occupancy(self.canonical_grid, posed_box, config.occupancy_resolution)

        pixels = self._draw_pixels(index)
        target_rgb = data.images[index][pixels[:, 1], pixels[:, 0]].to(device, torch.float32) / 255.0
        target_mask = data.masks[index][pixels[:, 1], pixels[:, 0]].to(device, torch.float32)
        background = torch.rand(target_rgb.shape, generator=self.generator).to(device)
        target = torch.where(target_mask[:, None] > 0.5, target_rgb, background)

        origins, directions = pixel_rays(data.K[index].to(device), data.w2c[index].to(device), pixels.to(device, torch.float32))
        rays = rays_in_box(origins, directions, posed_box[0], posed_box[1])
        sample_generator = torch.Generator(device=device).manual_seed(int(torch.randint(0, 2**62, (1,), generator=self.generator)))
        screen_pairs = config.regularizer == "smooth" and config.smooth_pairs == "screen"
        samples = sample_along_rays(
            rays, config.samples_per_ray, posed_grid.is_occupied, generator=sample_generator, compact=not screen_pairs
        )

        # Map every kept posed sample to canonical space once; samples without a root are empty.
        canonical_samples, x_rigid = posed.canonical_samples(samples)
        refining = self._refining(index)
        if refining:
            pose_generator = torch.Generator().manual_seed(config.seed * 104729 + self.step)
            canonical_samples, x_rigid = with_pose_gradient(self.avatar.deformer, posed.frame, samples, canonical_samples,
                                                            x_rigid, config.pose_gradient_samples, pose_generator)

        noise_std = config.sigma_noise_std if self.step < config.sigma_noise_steps else 0.0
        field_generator = torch.Generator(device=device).manual_seed(self.step + 1)

        def field_fn(x_canonical: torch.Tensor):
            return posed.fields_at(x_canonical, sigma_noise_std=noise_std, generator=field_generator)

        out = render_rays(canonical_samples, field_fn, background)
        if self.error_map is not None:
            self.error_map.record(index, pixels, (out.rgb.detach() - target).abs().mean(dim=-1))
        rendered = out.rgb_with_weights_gradient(background, self._weights_gradient_scale(index, pixels))
        terms = {"rgb": rgb_loss(rendered, target), "alpha": alpha_loss(out.opacity, target_mask)}
        terms.update(self._regularizer_terms(out, canonical_samples, x_rigid, posed.pose_condition))
        if self.hull is not None and config.loss_weights.free_space > 0:
            terms["free_space"] = self._free_space_term()
        if self.body_inside is not None:
            terms["body_inside"] = self._body_inside_term()
        loss = total_loss(terms, config.loss_weights)
        if refining:
            loss = loss + self.pose_refiner.regularization(index, config.pose_prior_weight, config.pose_translation_scale_m)

        self.optimizer.zero_grad(set_to_none=True)
        if self.table_optimizer is not None:
            self.table_optimizer.zero_grad(set_to_none=True)
        if self.pose_optimizer is not None:
            self.pose_optimizer.zero_grad(set_to_none=True)
        # A step whose rays hit no valid sample (all patches in empty space) has a constant loss:
        # nothing to learn from it, so it is counted but not stepped.
        if loss.requires_grad:
            loss.backward()
            self.optimizer.step()
            if self.table_optimizer is not None:
                self.table_optimizer.step()
            if refining:
                self.pose_optimizer.step()
        self.step += 1

        num_samples = int(canonical_samples.valid.sum())
        self.samples_seen += num_samples
        self.rays_seen += rays.num_rays
        elapsed = time.perf_counter() - started
        self.seconds += elapsed
        logs = {name: float(value.detach()) for name, value in terms.items()}
        logs.update(
            loss=float(loss.detach()), psnr=psnr_from_mse(float(((out.rgb.detach() - target) ** 2).mean())),
            beta=float(self.avatar.density.beta.detach()), samples=num_samples, step_seconds=elapsed,
            occupied=self.canonical_grid.occupied_fraction, lr=self.param_groups()[0]["lr"],
        )
        if self.pose_refiner is not None:
            logs.update(self.pose_refiner.correction_magnitudes())
        return logs

    def _refining(self, index: int) -> bool:
        """Whether this step updates frame `index`'s pose corrections."""
        return (self.pose_refiner is not None and self.pose_refiner.refines(index)
                and self.step >= int(self.config.pose_refine_start_fraction * self.total_steps))

    # ------------------------------------------------------------------ validation
    def render_frame(self, index: int, scale: float, num_samples: int) -> ImageRender:
        """Render dataset frame `index` from its own camera at `scale` x its resolution (white bg)."""
        data = self.data
        height, width = data.image_size
        h, w = max(8, round(height * scale)), max(8, round(width * scale))
        K = data.K[index].clone()
        K[0] *= w / width
        K[1] *= h / height
        K[0, 2] += 0.5 * w / width - 0.5
        K[1, 2] += 0.5 * h / height - 0.5
        self.avatar.eval()
        return render_avatar_view(
            self.avatar, self.canonical_grid, self.frame_transforms(index).detach(),
            data.pose_condition[index].to(self.device), K.to(self.device), data.w2c[index].to(self.device),
            h, w, data.posed_boxes[index].to(self.device), num_samples=num_samples,
            occupancy_resolution=self.config.occupancy_resolution,
        )

    # ------------------------------------------------------------------ state
    def state_dict(self) -> dict:
        """Everything needed to continue exactly: weights, Adam, RNG, occupancy, counters."""
        return {
            "avatar": self.avatar.state_dict(),
            "optimizer": self.optimizer.state_dict(),
            "table_optimizer": self.table_optimizer.state_dict() if self.table_optimizer is not None else None,
            "canonical_grid": self.canonical_grid.state_dict(),
            "generator": self.generator.get_state(),
            "step": self.step,
            "seconds": self.seconds,
            "samples_seen": self.samples_seen,
            "rays_seen": self.rays_seen,
            "pose_refiner": None if self.pose_refiner is None else self.pose_refiner.state_dict(),
            "pose_optimizer": None if self.pose_optimizer is None else self.pose_optimizer.state_dict(),
            "error_map": None if self.error_map is None else self.error_map.state_dict(),
            "pose_align_reports": self.pose_align_reports,
            "pose_silhouette": None if self.pose_silhouette is None else self.pose_silhouette.state(),
        }

    def load_state_dict(self, state: dict) -> None:
        self.avatar.load_state_dict(state["avatar"])
        # A saved optimizer carries its implementation flags (fused/foreach) in its groups; keep
        # this process's choice, so a run resumed with IGAVATAR_KERNELS=0 stays on the reference.
        flags = [{key: group.get(key) for key in ("fused", "foreach")} for group in self.optimizer.param_groups]
        self.optimizer.load_state_dict(state["optimizer"])
        for group, saved in zip(self.optimizer.param_groups, flags):
            group.update(saved)
        if self.table_optimizer is not None:
            self.table_optimizer.load_state_dict(state["table_optimizer"])
        self.canonical_grid.load_state_dict(state["canonical_grid"])
        self.generator.set_state(state["generator"].to(torch.uint8))
        self.step = int(state["step"])
        self.seconds = float(state["seconds"])
        self.samples_seen = int(state["samples_seen"])
        self.rays_seen = int(state["rays_seen"])
        if self.pose_refiner is not None:
            self.pose_refiner.load_state_dict(state["pose_refiner"])
            self.pose_optimizer.load_state_dict(state["pose_optimizer"])
            self.pose_align_reports = [dict(report) for report in state.get("pose_align_reports", [])]
        if self.error_map is not None:
            self.error_map.load_state_dict(state["error_map"])
        self._prepared.clear()
