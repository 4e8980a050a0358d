"""Fast-SNARF deformer: forward LBS through a voxel grid and its inverse by Broyden root finding.

    deformer = FastSnarfDeformer(weights_grid, box_min, box_max, DeformerConfig(init_bones=SMPL_INIT_BONES))
    frame = deformer.prepare(bone_transforms); x_cand, valid = deformer.canonicalize(x_posed, frame)

Forward skinning `LBS(x_c) = sum_j w_j(x_c) B_j x_c` uses the per-frame blended transform grid
`T = sum_j w_j B_j` (one trilinear lookup per point). Canonicalisation solves `LBS(x_c) = x_d` for
every posed point from several starts (`x_d` rigidly un-posed by each init bone), with Broyden's
"good" update of the inverse Jacobian, initialized at `(sum_j w_j R_j)^-1` (dw/dx ignored, as
Fast-SNARF). A root is valid when it converged, lies inside the grid box and is not a duplicate of
an earlier valid root of the same point. With `init_top_k` only the best-ranked starts are run; a
point none of whose kept starts converged tries the rest (`fallback_starts`). Root finding runs
without autograd; gradients come back through `attach_implicit_gradient` (implicit function
theorem).

Every method takes its frame data from the `PreparedFrame` it is given: no state is kept between
calls, and tensors may live on any device.

Fast path: on CPU float32 tensors the root finding, the start selection and no-grad forward LBS
run in the C++ kernel ``igavatar/kernels/csrc/skinning.cpp`` (one start per loop iteration, all
state in registers, channel-last grids). ``_broyden_reference`` and the ``sample_grid`` lookups are
the PyTorch reference it is tested against; ``IGAVATAR_KERNELS=0`` uses them everywhere.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import nn

from igavatar.errors import InputError
from igavatar.kernels import load_kernel
from igavatar.model.linear import linear
from igavatar.skinning.grid import (
    apply_affine,
    blended_transform_grid,
    inside_grid,
    sample_blended_transforms,
    sample_grid,
)

__all__ = [
    "SMPL_INIT_BONES",
    "DeformerConfig",
    "PreparedFrame",
    "FastSnarfDeformer",
    "select_candidates",
]

SMPL_INIT_BONES: tuple[int, ...] = (0, 1, 2, 4, 5, 10, 11, 12, 15, 16, 17, 18, 19)
"""The 13 major SMPL bones Fast-SNARF starts root finding from (pelvis, hips, knees, feet, neck,
collars, head, shoulders)."""


@dataclass(frozen=True)
class DeformerConfig:
    """Root-finding settings (defaults: Fast-SNARF's)."""

    max_iterations: int = 10
    """Broyden iterations per start point."""
    converge_threshold: float = 1e-5
    """A start converged when |LBS(x_c) - x_d| < this (world units, meters)."""
    diverge_threshold: float = 0.1
    """A start stops iterating once its current residual norm exceeds this."""
    duplicate_threshold: float = 1e-4
    """A valid root closer than this to an earlier valid root of the same point is dropped."""
    init_bones: tuple[int, ...] | None = None
    """Bones whose inverse transforms give the start points; None = every bone of the grid.
    For SMPL use `SMPL_INIT_BONES`."""
    init_top_k: int | None = None
    """If set, keep per point only the k starts whose bone has the largest skinning weight at
    its own rigidly un-posed start (self-consistent starts first); None keeps all starts."""
    init_parts: tuple[int, ...] | None = None
    """Per bone of the grid, the position in `init_bones` of the start bone that stands for it
    (`init_parts`): the `init_top_k` selection then ranks a start by the summed weight of its
    part, not of its bone alone. None: the bone's own weight. Without it, where a body's own
    weights give a limb to bones that start no search (the knee to a twist bone, the ankle to
    the foot's children), no start looks self-consistent and the top-k keep the wrong ones."""
    fallback_starts: bool = True
    """With `init_top_k`: a point none of whose k starts converged tries the other starts (its k
    candidates are then the first of those that converged)."""
    chunk_size: int = 32768
    """Posed points processed together by `canonicalize` (bounds peak memory)."""

    def __post_init__(self) -> None:
        if self.max_iterations < 0:
            raise InputError(f"DeformerConfig.max_iterations: {self.max_iterations}, expected >= 0")
        if not 0 < self.converge_threshold < self.diverge_threshold:
            raise InputError(
                "DeformerConfig: expected 0 < converge_threshold < diverge_threshold, got "
                f"{self.converge_threshold} and {self.diverge_threshold}"
            )
        if self.duplicate_threshold < 0:
            raise InputError(
                f"DeformerConfig.duplicate_threshold: {self.duplicate_threshold}, expected >= 0"
            )
        if self.init_bones is not None and len(self.init_bones) == 0:
            raise InputError("DeformerConfig.init_bones: empty; give bone indices or None (all)")
        if self.init_top_k is not None and self.init_top_k < 1:
            raise InputError(f"DeformerConfig.init_top_k: {self.init_top_k}, expected >= 1 or None")
        if self.init_parts is not None:
            starts = len(self.init_bones) if self.init_bones is not None else len(self.init_parts)
            if any(not 0 <= p < starts for p in self.init_parts):
                raise InputError(f"DeformerConfig.init_parts: entries must index init_bones (0..{starts - 1})")
        if self.chunk_size < 1:
            raise InputError(f"DeformerConfig.chunk_size: {self.chunk_size}, expected >= 1")


def init_parts(parents: Sequence[int], init_bones: Sequence[int]) -> tuple[int, ...]:
    """Each bone's part: the position in `init_bones` of its nearest ancestor-or-self among them.

    A bone with no start bone above it (only possible when the root is not one) joins the first.

    Args:
        parents: (J,) parent index per bone, -1 at the root. init_bones: (I0,) bone indices.
    Returns:
        J entries in 0..I0-1 (DeformerConfig.init_parts).
    """
    position = {int(b): i for i, b in enumerate(init_bones)}
    parts = []
    for bone in range(len(parents)):
        k = bone
        while k >= 0 and k not in position:
            k = int(parents[k])
        parts.append(position[k] if k >= 0 else 0)
    return tuple(parts)


@dataclass(frozen=True)
class PreparedFrame:
    """Everything the deformer needs about one frame; built by `FastSnarfDeformer.prepare`.

    Tensors keep their autograd history, so gradients reach the bone transforms (and the weight
    grid, if it requires grad) through `forward_skinning` and `attach_implicit_gradient`.
    """

    blended_grid: torch.Tensor
    """(12, D, H, W) per-voxel `sum_j w_j B_j[:3, :]`."""
    weights_grid: torch.Tensor
    """(J, D, H, W) skinning weights the blended grid was made from."""
    box_min: torch.Tensor
    """(3,) canonical grid box corner."""
    box_max: torch.Tensor
    """(3,) canonical grid box corner."""
    bone_transforms: torch.Tensor
    """(J, 4, 4) canonical -> posed world bone transforms."""
    init_bones: torch.Tensor
    """(I0,) long indices of the bones whose inverses give start points."""
    init_inverse: torch.Tensor
    """(I0, 3, 4) top rows of `inverse(B_i)` for the init bones (posed -> canonical, rigid)."""
    blended_grid_last: torch.Tensor | None = None
    """(D, H, W, 12) channel-last copy of `blended_grid` for the C++ kernel (None: no kernel)."""
    init_weights_last: torch.Tensor | None = None
    """(D, H, W, I0) channel-last init-bone weights for the kernel's start selection (or None)."""

    @property
    def num_candidates(self) -> int:
        """Candidates per point that `canonicalize` returns for this frame (I)."""
        return int(self.init_bones.shape[0])


def select_candidates(
    candidates: torch.Tensor, valid: torch.Tensor, score: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Pick per point the valid candidate with the highest score (e.g. density).

    Args:
        candidates: (P, I, 3) canonical candidates.
        valid: (P, I) bool.
        score: (P, I) higher is better.
    Returns:
        x (P, 3) the chosen candidates (candidate 0 where none is valid), any_valid (P,) bool.
    """
    if candidates.ndim != 3 or valid.shape != candidates.shape[:2] or score.shape != valid.shape:
        raise InputError(
            f"select_candidates: shapes {tuple(candidates.shape)}, {tuple(valid.shape)}, "
            f"{tuple(score.shape)}; expected (P, I, 3), (P, I), (P, I)"
        )
    masked = torch.where(valid, score, torch.full_like(score, float("-inf")))
    # nan scores would win argmax; they count as the worst valid score instead
    masked = torch.nan_to_num(masked, nan=torch.finfo(score.dtype).min)
    best = masked.argmax(dim=1)
    any_valid = valid.any(dim=1)
    best = torch.where(any_valid, best, torch.zeros_like(best))
    chosen = torch.gather(candidates, 1, best[:, None, None].expand(-1, 1, 3)).squeeze(1)
    return chosen, any_valid


def _skinning_kernel(*tensors: torch.Tensor):
    """The compiled skinning kernel when every tensor is a float32 CPU tensor, else None."""
    if not all(t.device.type == "cpu" and t.dtype == torch.float32 for t in tensors):
        return None
    return load_kernel("skinning")


def _lbs_and_transform(frame: PreparedFrame, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(N, 3) canonical -> posed (N, 3) and the blended transforms (N, 3, 4) used."""
    transforms = sample_blended_transforms(frame.blended_grid, frame.box_min, frame.box_max, x)
    return apply_affine(transforms, x), transforms


def _safe_inverse(matrices: torch.Tensor) -> torch.Tensor:
    """Batched 3x3 inverse by the adjugate (much cheaper than LU for tiny matrices).

    (N, 3, 3) -> (N, 3, 3); (near-)singular matrices, |det| <= 1e-12, get the identity instead of
    inf/nan, so a degenerate blend (opposed rotations) stalls a start instead of poisoning it.
    """
    a, b, c = matrices[:, 0, 0], matrices[:, 0, 1], matrices[:, 0, 2]
    d, e, f = matrices[:, 1, 0], matrices[:, 1, 1], matrices[:, 1, 2]
    g, h, i = matrices[:, 2, 0], matrices[:, 2, 1], matrices[:, 2, 2]
    cofactor_a, cofactor_b, cofactor_c = e * i - f * h, f * g - d * i, d * h - e * g
    determinant = a * cofactor_a + b * cofactor_b + c * cofactor_c
    adjugate = torch.stack(
        [
            cofactor_a, c * h - b * i, b * f - c * e,
            cofactor_b, a * i - c * g, c * d - a * f,
            cofactor_c, b * g - a * h, a * e - b * d,
        ],
        dim=-1,
    ).reshape(-1, 3, 3)
    regular = determinant.abs() > 1e-12
    safe_determinant = torch.where(regular, determinant, torch.ones_like(determinant))
    identity = torch.eye(3, dtype=matrices.dtype, device=matrices.device)
    return torch.where(regular[:, None, None], adjugate / safe_determinant[:, None, None], identity)


def _broyden(
    frame: PreparedFrame,
    x_target: torch.Tensor,
    x_init: torch.Tensor,
    config: DeformerConfig,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Solve LBS(x) = x_target from x_init: the C++ kernel when it applies, else the reference."""
    kernel = _skinning_kernel(x_target, x_init) if frame.blended_grid_last is not None else None
    if kernel is None:
        return _broyden_reference(frame, x_target, x_init, config)
    x_best, residual_best = kernel.broyden(
        frame.blended_grid_last, frame.box_min, frame.box_max, x_target.contiguous(), x_init.contiguous(),
        config.max_iterations, config.converge_threshold, config.diverge_threshold,
    )
    return x_best, residual_best


def _broyden_reference(
    frame: PreparedFrame,
    x_target: torch.Tensor,
    x_init: torch.Tensor,
    config: DeformerConfig,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Solve LBS(x) = x_target from x_init with Broyden's good method (plain PyTorch).

    Args:
        x_target: (N, 3) posed points (one per start).
        x_init: (N, 3) start points in canonical space.
    Returns:
        x_best (N, 3) the iterate with the smallest residual, residual_best (N,) its norm.
    """
    x_posed, transforms = _lbs_and_transform(frame, x_init)
    residual = x_posed - x_target
    jacobian_inverse = _safe_inverse(transforms[:, :, :3])
    x_best = x_init.clone()
    residual_best = residual.norm(dim=-1)

    # Only unconverged starts are iterated, compacted to the front: `active` maps the rows back to
    # the N starts. One nonzero + index_select per shrink; boolean-mask indexing would pay a
    # nonzero per tensor.
    active = torch.nonzero(residual_best > config.converge_threshold).squeeze(1)
    x = x_init.index_select(0, active)
    residual = residual.index_select(0, active)
    jacobian_inverse = jacobian_inverse.index_select(0, active)
    target = x_target.index_select(0, active)
    x_best_active = x
    norm_best_active = residual_best.index_select(0, active)
    for _ in range(config.max_iterations):
        if active.numel() == 0:
            break
        step = -(jacobian_inverse @ residual.unsqueeze(-1)).squeeze(-1)
        x = x + step
        residual_new = _lbs_and_transform(frame, x)[0] - target
        residual_change = residual_new - residual
        residual = residual_new
        norm = residual.norm(dim=-1)

        improved = norm < norm_best_active
        norm_best_active = torch.where(improved, norm, norm_best_active)
        x_best_active = torch.where(improved.unsqueeze(-1), x, x_best_active)

        keep = (norm_best_active > config.converge_threshold) & (norm < config.diverge_threshold)
        if not bool(keep.all()):
            x_best.index_copy_(0, active, x_best_active)
            residual_best.index_copy_(0, active, norm_best_active)
            rows = torch.nonzero(keep).squeeze(1)
            (active, x, residual, target, jacobian_inverse, step, residual_change,
             x_best_active, norm_best_active) = (
                t.index_select(0, rows)
                for t in (
                    active, x, residual, target, jacobian_inverse, step, residual_change,
                    x_best_active, norm_best_active,
                )
            )
            if active.numel() == 0:
                break

        # Good Broyden: H += (dx - H dg) dx^T H / (dx^T H dg). Since dg ~ J dx, the denominator is
        # ~|dx|^2; far below that the secant pair carries no information and H is left as is.
        v = (step.unsqueeze(1) @ jacobian_inverse).squeeze(1)
        denominator = (v * residual_change).sum(dim=-1)
        usable = denominator.abs() > 1e-6 * step.square().sum(dim=-1)
        numerator = step - (jacobian_inverse @ residual_change.unsqueeze(-1)).squeeze(-1)
        scale = torch.where(usable, 1.0 / torch.where(usable, denominator, 1.0), 0.0)
        jacobian_inverse = jacobian_inverse + (numerator * scale.unsqueeze(-1)).unsqueeze(-1) * v.unsqueeze(1)
    x_best.index_copy_(0, active, x_best_active)
    residual_best.index_copy_(0, active, norm_best_active)
    return x_best, residual_best


def _remove_duplicates(candidates: torch.Tensor, valid: torch.Tensor, threshold: float) -> torch.Tensor:
    """Mark a valid candidate invalid if an earlier, still-valid candidate of its point is within
    `threshold` (sequential over I, as Fast-SNARF's kernel, vectorised over points).

    Args:
        candidates: (P, I, 3); valid: (P, I) bool.
    Returns:
        (P, I) bool.
    """
    num_candidates = candidates.shape[1]
    if num_candidates < 2:
        return valid
    valid = valid.clone()
    for i in range(1, num_candidates):
        # Explicit differences: cdist's matmul path loses ~1e-4 m to cancellation in float32.
        distance = (candidates[:, :i] - candidates[:, i : i + 1]).norm(dim=-1)
        duplicate = (valid[:, :i] & (distance < threshold)).any(dim=1)
        valid[:, i] &= ~duplicate
    return valid


class FastSnarfDeformer(nn.Module):
    """Fast-SNARF forward/inverse skinning over a canonical weight grid (no learnable parameters).

    The weight grid and box are buffers (they follow `.to(device)` and the state dict). To refine
    skinning weights, make `weights_grid` require grad; gradients then flow through `prepare`.
    """

    def __init__(
        self,
        weights_grid: torch.Tensor,
        box_min: torch.Tensor,
        box_max: torch.Tensor,
        config: DeformerConfig = DeformerConfig(),
    ) -> None:
        """
        Args:
            weights_grid: (J, D, H, W) skinning weights (e.g. `build_skinning_grid`).
            box_min, box_max: (3,) canonical grid box.
            config: root-finding settings.
        """
        super().__init__()
        if weights_grid.ndim != 4:
            raise InputError(f"weights_grid: shape {tuple(weights_grid.shape)}, expected (J, D, H, W)")
        if box_min.shape != (3,) or box_max.shape != (3,) or not bool((box_max > box_min).all()):
            raise InputError(
                f"box_min/box_max: {box_min.tolist()} / {box_max.tolist()}, expected (3,) each "
                "with box_max > box_min"
            )
        num_joints = weights_grid.shape[0]
        if config.init_bones is not None:
            bad = [b for b in config.init_bones if not 0 <= b < num_joints]
            if bad:
                raise InputError(
                    f"DeformerConfig.init_bones: {bad} out of range for a grid with {num_joints} joints"
                )
        if config.init_parts is not None and len(config.init_parts) != num_joints:
            raise InputError(
                f"DeformerConfig.init_parts: {len(config.init_parts)} entries, expected one per bone ({num_joints})"
            )
        self.config = config
        self.register_buffer("weights_grid", weights_grid)
        self.register_buffer("box_min", box_min.to(weights_grid.dtype))
        self.register_buffer("box_max", box_max.to(weights_grid.dtype))

    @property
    def num_joints(self) -> int:
        """J, the number of bones of the weight grid."""
        return int(self.weights_grid.shape[0])

    def prepare(self, bone_transforms: torch.Tensor) -> PreparedFrame:
        """Per-frame precomputation: blended transform grid and inverse init-bone transforms.

        Args:
            bone_transforms: (J, 4, 4) canonical -> posed world transforms of one frame.
        Returns:
            a PreparedFrame for `forward_skinning`, `canonicalize`, `attach_implicit_gradient`.
        """
        if bone_transforms.shape != (self.num_joints, 4, 4):
            raise InputError(
                f"bone_transforms: shape {tuple(bone_transforms.shape)}, expected "
                f"({self.num_joints}, 4, 4) to match the weight grid"
            )
        bone_transforms = bone_transforms.to(self.weights_grid.dtype)
        device = self.weights_grid.device
        if self.config.init_bones is None:
            init_bones = torch.arange(self.num_joints, device=device)
        else:
            init_bones = torch.tensor(self.config.init_bones, dtype=torch.long, device=device)
        # Start points are computed without autograd, so the inverse needs no history.
        init_inverse = torch.linalg.inv(bone_transforms.detach()[init_bones])[:, :3, :]
        blended_last = init_weights_last = None
        if _skinning_kernel(self.weights_grid) is not None and not self.weights_grid.requires_grad:
            # The kernel reads channel-last grids (a lookup = 8 runs of adjacent floats). The
            # blended grid is built in that layout and the reference layout is a view of it, so a
            # prepared frame costs no more memory than before.
            weights_last, init_weights_last = self._channel_last_weights(init_bones)
            affine = bone_transforms[:, :3, :].reshape(self.num_joints, 12).to(weights_last.dtype)
            # (D*H*W, J) x (J, 12) through oneDNN (linear.py; the grid's shape is fixed, so its
            # kernel is compiled once): half the time of the default matrix product here.
            blended_last = linear(weights_last.reshape(-1, self.num_joints), affine.t()).reshape(
                *weights_last.shape[:3], 12
            )  # (D, H, W, 12)
            blended_grid = blended_last.permute(3, 0, 1, 2)
        else:
            blended_grid = blended_transform_grid(self.weights_grid, bone_transforms)
        return PreparedFrame(
            blended_grid=blended_grid,
            weights_grid=self.weights_grid,
            box_min=self.box_min,
            box_max=self.box_max,
            bone_transforms=bone_transforms,
            init_bones=init_bones,
            init_inverse=init_inverse,
            blended_grid_last=None if blended_last is None else blended_last.detach(),
            init_weights_last=init_weights_last,
        )

    def _start_weight_grid(self, init_bones: torch.Tensor) -> torch.Tensor:
        """(I0, D, H, W) the weight each start bone is ranked by: its part's summed weight with
        `init_parts`, else its own; made once per grid, starts and device (like the channel-last copy)."""
        grid = self.weights_grid
        key = (grid.data_ptr(), grid._version, grid.device, tuple(init_bones.tolist()))
        cached = getattr(self, "_start_weights_cache", None)
        if cached is None or cached[0] != key:
            weights = grid.detach()
            if self.config.init_parts is None:
                start = weights[init_bones]
            else:
                index = torch.tensor(self.config.init_parts, dtype=torch.long, device=weights.device)
                start = weights.new_zeros((len(init_bones), *weights.shape[1:])).index_add_(0, index, weights)
            cached = (key, start)
            self._start_weights_cache = cached
        return cached[1]

    def _channel_last_weights(self, init_bones: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(D, H, W, J) weights and (D, H, W, I0) init-bone weights, made once per grid and device."""
        # _version changes on in-place writes (load_state_dict), data_ptr on moves and replacements.
        grid = self.weights_grid
        key = (grid.data_ptr(), grid._version, grid.device, tuple(init_bones.tolist()))
        cached = getattr(self, "_weights_last_cache", None)
        if cached is None or cached[0] != key:
            weights_last = grid.detach().permute(1, 2, 3, 0).contiguous()
            cached = (key, weights_last, self._start_weight_grid(init_bones).permute(1, 2, 3, 0).contiguous())
            self._weights_last_cache = cached
        return cached[1], cached[2]

    def candidates_per_point(self, frame: PreparedFrame) -> int:
        """I, the candidate count per point of `canonicalize` for this frame."""
        if self.config.init_top_k is None:
            return frame.num_candidates
        return min(self.config.init_top_k, frame.num_candidates)

    def forward_skinning(self, x_canonical: torch.Tensor, frame: PreparedFrame) -> torch.Tensor:
        """LBS of canonical points: (P, 3) -> posed world (P, 3); differentiable in x and frame."""
        _check_points(x_canonical, "x_canonical")
        x = x_canonical.to(frame.blended_grid.dtype)
        recording = torch.is_grad_enabled() and (x.requires_grad or frame.blended_grid.requires_grad)
        kernel = _skinning_kernel(x) if frame.blended_grid_last is not None and not recording else None
        if kernel is not None:
            return kernel.lbs(frame.blended_grid_last, frame.box_min, frame.box_max, x.contiguous())
        return _lbs_and_transform(frame, x)[0]

    def initial_points(self, x_posed: torch.Tensor, frame: PreparedFrame) -> torch.Tensor:
        """Start points: posed points rigidly un-posed by each init bone, (P, 3) -> (P, I, 3).

        With `init_top_k`, only the k starts with the largest self-weight `w_b(B_b^-1 x_d)` are
        kept, ordered by that weight (largest first).
        """
        return self.ranked_starts(x_posed, frame)[:, : self.candidates_per_point(frame)]

    def ranked_starts(self, x_posed: torch.Tensor, frame: PreparedFrame) -> torch.Tensor:
        """Every start point, (P, 3) -> (P, I0, 3); with `init_top_k`, ordered by self-weight
        `w_b(B_b^-1 x_d)`, largest first (the order `initial_points` keeps the first k of)."""
        inverse = frame.init_inverse.to(x_posed.dtype)
        x_init = torch.einsum("irc,pc->pir", inverse[:, :, :3], x_posed) + inverse[:, :, 3]
        if self.config.init_top_k is None or self.config.init_top_k >= frame.num_candidates:
            return x_init
        num_points, num_init = x_init.shape[:2]
        kernel = _skinning_kernel(x_init) if frame.init_weights_last is not None else None
        if kernel is not None:
            self_weight = kernel.sample_diagonal(frame.init_weights_last, frame.box_min, frame.box_max, x_init.contiguous())
        else:
            init_weights = sample_grid(
                self._start_weight_grid(frame.init_bones), frame.box_min, frame.box_max, x_init.reshape(-1, 3),
            ).reshape(num_points, num_init, num_init)
            self_weight = torch.diagonal(init_weights, dim1=1, dim2=2)
        order = self_weight.topk(num_init, dim=1).indices
        return torch.gather(x_init, 1, order.unsqueeze(-1).expand(-1, -1, 3))

    @torch.no_grad()
    def canonicalize(
        self, x_posed: torch.Tensor, frame: PreparedFrame
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """All canonical correspondences of posed points (no autograd).

        Args:
            x_posed: (P, 3) posed world points.
            frame: from `prepare`.
        Returns:
            x_canonical_candidates (P, I, 3) and valid (P, I) bool: converged, inside the grid box
            and not a duplicate of an earlier valid candidate. Invalid rows hold the best iterate.
        """
        _check_points(x_posed, "x_posed")
        x_posed = x_posed.detach().to(frame.blended_grid.dtype)
        num_candidates = self.candidates_per_point(frame)
        if x_posed.shape[0] == 0:
            empty = x_posed.new_zeros((0, num_candidates, 3))
            return empty, torch.zeros((0, num_candidates), dtype=torch.bool, device=x_posed.device)
        # The frame may carry autograd history (pose refinement); root finding must not.
        frame_detached = PreparedFrame(
            blended_grid=frame.blended_grid.detach(),
            weights_grid=frame.weights_grid.detach(),
            box_min=frame.box_min,
            box_max=frame.box_max,
            bone_transforms=frame.bone_transforms.detach(),
            init_bones=frame.init_bones,
            init_inverse=frame.init_inverse.detach(),
            blended_grid_last=frame.blended_grid_last,
            init_weights_last=frame.init_weights_last,
        )
        candidates, valid = [], []
        for chunk in x_posed.split(self.config.chunk_size):
            chunk_candidates, chunk_valid = self._canonicalize_chunk(chunk, frame_detached)
            candidates.append(chunk_candidates)
            valid.append(chunk_valid)
        return torch.cat(candidates), torch.cat(valid)

    def _canonicalize_chunk(
        self, x_posed: torch.Tensor, frame: PreparedFrame
    ) -> tuple[torch.Tensor, torch.Tensor]:
        starts = self.ranked_starts(x_posed, frame)
        num_candidates = self.candidates_per_point(frame)
        x_root, valid = self._solve(frame, x_posed, starts[:, :num_candidates])
        if self.config.fallback_starts and num_candidates < starts.shape[1]:
            x_root, valid = self._fall_back(frame, x_posed, starts[:, num_candidates:], x_root, valid)
        valid = _remove_duplicates(x_root, valid, self.config.duplicate_threshold)
        return x_root, valid

    def _solve(self, frame: PreparedFrame, x_posed: torch.Tensor, x_init: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Roots of (P, 3) posed points from (P, K, 3) starts: (P, K, 3) and valid (P, K) (converged,
        inside the grid; duplicates not yet removed)."""
        num_points, num_candidates = x_init.shape[:2]
        x_target = x_posed.unsqueeze(1).expand(-1, num_candidates, -1).reshape(-1, 3)
        x_root, residual = _broyden(frame, x_target, x_init.reshape(-1, 3), self.config)
        valid = (residual < self.config.converge_threshold) & inside_grid(frame.box_min, frame.box_max, x_root)
        return x_root.reshape(num_points, num_candidates, 3), valid.reshape(num_points, num_candidates)

    def _fall_back(self, frame: PreparedFrame, x_posed: torch.Tensor, rest: torch.Tensor, x_root: torch.Tensor,
                   valid: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Points none of whose K kept starts converged try their (P, R, 3) `rest`; their K slots
        take the first converged roots of those, in rank order.

        Where two limbs meet in a pose (a hand at the hip), the other limb's bones look
        self-consistent at the first limb's points and can fill every kept start.
        """
        lost = torch.nonzero(~valid.any(dim=1)).squeeze(1)
        if lost.numel() == 0:
            return x_root, valid
        rest_root, rest_valid = self._solve(frame, x_posed.index_select(0, lost), rest.index_select(0, lost))
        slots = min(valid.shape[1], rest.shape[1])
        # Converged roots first, each group in rank order (a stable sort on "not converged").
        pick = torch.sort((~rest_valid).to(torch.uint8), dim=1, stable=True).indices[:, :slots]
        # In place: both tensors are this chunk's own, fresh from `_solve`.
        x_root[lost, :slots] = torch.gather(rest_root, 1, pick.unsqueeze(-1).expand(-1, -1, 3))
        valid[lost, :slots] = torch.gather(rest_valid, 1, pick)
        return x_root, valid

    def lbs_jacobian(self, x_canonical: torch.Tensor, frame: PreparedFrame) -> torch.Tensor:
        """Full Jacobian d LBS / d x_c (including the d w / d x term), detached.

        Args:
            x_canonical: (P, 3).
        Returns:
            (P, 3, 3), entry [p, r, c] = d LBS(x_p)_r / d x_c.
        """
        _check_points(x_canonical, "x_canonical")
        blended = frame.blended_grid.detach()
        with torch.enable_grad():
            x = x_canonical.detach().to(blended.dtype).requires_grad_(True)
            transforms = sample_blended_transforms(blended, frame.box_min, frame.box_max, x)
            x_posed = apply_affine(transforms, x)
            # Points are independent, so the gradient of a column sum is that row of each Jacobian.
            rows = [
                torch.autograd.grad(x_posed[:, r].sum(), x, retain_graph=r < 2)[0] for r in range(3)
            ]
        return torch.stack(rows, dim=1)

    def attach_implicit_gradient(
        self, x_canonical: torch.Tensor, x_posed: torch.Tensor, frame: PreparedFrame
    ) -> torch.Tensor:
        """Give a detached root x_c of LBS(x_c; frame) = x_d its implicit-function gradients.

        With g(x_c, x_d, theta) = LBS(x_c; theta) - x_d = 0, the implicit function theorem gives
        dx_c/dx_d = J^-1 and dx_c/dtheta = -J^-1 dLBS/dtheta, J = dLBS/dx_c at the root. So
        `x_c = x_hat - J^-1 (g - g.detach())` has value x_hat and exactly those gradients (w.r.t.
        x_posed, and through the frame w.r.t. bone transforms and weight grid).

        Args:
            x_canonical: (P, 3) roots (their autograd history is dropped).
            x_posed: (P, 3) the posed points they solve for.
            frame: the PreparedFrame used to find them.
        Returns:
            (P, 3), equal in value to x_canonical.
        """
        _check_points(x_canonical, "x_canonical")
        if x_posed.shape != x_canonical.shape:
            raise InputError(
                f"x_posed: shape {tuple(x_posed.shape)}, expected {tuple(x_canonical.shape)} "
                "like x_canonical"
            )
        x_hat = x_canonical.detach().to(frame.blended_grid.dtype)
        jacobian_inverse = _safe_inverse(self.lbs_jacobian(x_hat, frame))
        residual = self.forward_skinning(x_hat, frame) - x_posed.to(x_hat.dtype)
        correction = residual - residual.detach()
        return x_hat - (jacobian_inverse @ correction.unsqueeze(-1)).squeeze(-1)

    select_candidates = staticmethod(select_candidates)


def _check_points(x: torch.Tensor, name: str) -> None:
    if x.ndim != 2 or x.shape[-1] != 3:
        raise InputError(f"{name}: shape {tuple(x.shape)}, expected (P, 3)")
