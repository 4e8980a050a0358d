"""World boxes that bound a trained avatar in any pose (rendering and marching-cubes bounds).

    boxes = posed_boxes(model, bone_transforms, posed_joints)     # (N, 2, 3)

The centers of the canonical occupied cells are forward-skinned into each frame; because LBS of a
bounded canonical set stays bounded, any pose, however far from the training poses, gets a box
the size of the body, and no frame reuses another's empty-space skipping.
"""

from __future__ import annotations

import math

import torch

from igavatar.avatar.model import ModelArtifact

#: Extra padding (meters) of a posed box beyond the skinned canonical cells and the offset bound.
BOX_PADDING_M = 0.03
#: Padding (meters) around the posed joints when the canonical grid has no occupied cell.
JOINT_BOX_PADDING_M = 0.3


def canonical_cell_centers(model: ModelArtifact) -> torch.Tensor:
    """(C, 3) canonical centers of the occupied cells of the model's canonical occupancy grid."""
    grid = model.canonical_grid
    iz, iy, ix = torch.nonzero(grid.occupied, as_tuple=True)
    return grid.box_min + (torch.stack((ix, iy, iz), dim=-1).to(grid.box_min.dtype) + 0.5) * grid.cell_size()


@torch.no_grad()
def skinned_cells(model: ModelArtifact, bone_transforms: torch.Tensor, max_points: int | None = None) -> torch.Tensor:
    """Occupied canonical cell centers pushed through forward LBS: (N, C, 3) posed world points.

    Args:
        bone_transforms: (N, J, 4, 4) canonical -> posed world.
        max_points: keep every k-th cell so that C <= max_points (for framing); None keeps all.
    """
    x_canonical = canonical_cell_centers(model)
    if max_points is not None and x_canonical.shape[0] > max_points:
        x_canonical = x_canonical[:: -(-x_canonical.shape[0] // max_points)]
    deformer = model.avatar.deformer
    return torch.stack([
        deformer.forward_skinning(x_canonical, deformer.prepare(transforms.to(x_canonical.device)))
        for transforms in bone_transforms
    ])


@torch.no_grad()
def posed_boxes(model: ModelArtifact, bone_transforms: torch.Tensor, posed_joints: torch.Tensor) -> torch.Tensor:
    """World boxes (N, 2, 3) that bound the posed avatar in each frame.

    The box of the skinned cell centers is padded by half a cell diagonal (a cell's content
    around its center), the non-rigid offset bound when the offset is on (the surface moves at
    most that far from its rigid correspondence) and BOX_PADDING_M. Without occupied cells the
    posed joints padded by JOINT_BOX_PADDING_M are used.

    Args:
        bone_transforms: (N, J, 4, 4) canonical -> posed world; posed_joints: (N, J, 3).
    """
    if not bool(model.canonical_grid.occupied.any()):
        low, high = posed_joints.amin(dim=1), posed_joints.amax(dim=1)
        return torch.stack((low - JOINT_BOX_PADDING_M, high + JOINT_BOX_PADDING_M), dim=1)
    nonrigid = model.avatar.nonrigid
    # Each offset component is bounded by max_offset, so its length (after any rotation) by sqrt(3) x.
    offset_bound = math.sqrt(3.0) * nonrigid.config.max_offset if nonrigid.enabled else 0.0
    cell = model.canonical_grid.cell_size()
    pad = 0.5 * float(torch.linalg.vector_norm(cell)) + offset_bound + BOX_PADDING_M
    boxes = [
        torch.stack((x_posed.amin(dim=0) - pad, x_posed.amax(dim=0) + pad))
        for x_posed in (skinned_cells(model, transforms[None])[0] for transforms in bone_transforms)
    ]
    return torch.stack(boxes).to(torch.float32)
