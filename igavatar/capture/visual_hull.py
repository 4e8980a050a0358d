"""The masks' visual hull in canonical space: canonical points voted in or out of the training masks.

    views = MaskViews(masks, K, w2c, frames)                         # the training frames that vote
    votes = vote_masks(points_canonical, skin, views)                 # seen, inside: (P,) int32 each
    prior = hull_prior_mesh(hull_cells(box, skin, views, cell_size=0.02))  # a closed mesh of the hull

Forward skinning needs no root finding: `skin(frame, x_canonical)` pushes canonical points into a
frame's world space, where they are projected into its mask. A point that a robust number of views
see as background is free space; since the subject lies inside every mask, its surface lies inside
what is left. The trainer uses the free part as a lower bound of the SDF
(igavatar.training.visual_hull); preprocess meshes the kept part as the shape prior of a capture
with no body-model template (a bare skeleton, or a single root joint: a person standing still,
filmed from all around), where capsules around the bones would be a sliver or nothing at all.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch
from scipy import ndimage

from igavatar.capture.ghost_limbs import GhostTest, SkinFn, misplaced_votes


@dataclass(frozen=True)
class MaskViews:
    """The views that vote: one mask and camera per training frame.

    Attributes:
        masks: V arrays (H, W) bool, subject = True.
        K: (V, 3, 3) intrinsics of the masks' pixel grid.
        w2c: (V, 4, 4) world -> camera (OpenCV: +z forward).
        frames: V frame indices passed to the skin callable.
    """

    masks: Sequence[np.ndarray]
    K: np.ndarray
    w2c: np.ndarray
    frames: Sequence[int]


def spread_views(frames: Sequence[int], max_views: int) -> list[int]:
    """At most `max_views` of `frames`, evenly spaced (bounds the cost of a long capture)."""
    frames = list(frames)
    if len(frames) <= max_views:
        return frames
    return [frames[i] for i in np.linspace(0, len(frames) - 1, max_views).round().astype(int)]


def grid_points(box_min: torch.Tensor, box_max: torch.Tensor, cell_size: float) -> tuple[torch.Tensor, tuple[int, int, int]]:
    """Cell-corner points of a grid over the box (align_corners) as (D*H*W, 3) and the shape (D, H, W).

    Index order D<->z, H<->y, W<->x (as the skinning grid and `grid_sample`).
    """
    counts = [max(2, int(math.ceil(float(hi - lo) / cell_size)) + 1) for lo, hi in zip(box_min, box_max)]
    axes = [torch.linspace(float(lo), float(hi), n) for lo, hi, n in zip(box_min, box_max, counts)]
    z, y, x = torch.meshgrid(axes[2], axes[1], axes[0], indexing="ij")
    return torch.stack((x, y, z), dim=-1).reshape(-1, 3), (counts[2], counts[1], counts[0])


def grid_spacing(box_min: torch.Tensor, box_max: torch.Tensor, shape: tuple[int, int, int]) -> list[float]:
    """Meters between neighbouring points along (D, H, W) = (z, y, x) of a `grid_points` grid."""
    return [float(box_max[axis] - box_min[axis]) / (shape[2 - axis] - 1) for axis in (2, 1, 0)]


@dataclass(frozen=True)
class MaskVotes:
    """Per canonical point: views that see it, views whose mask holds it, views that crush it.

    Attributes:
        seen: (P,) int32 views in which the point projects into the image in front of the camera.
        inside: (P,) int32 views in which it falls inside the (dilated) mask.
        collapsed: (P,) int32 views in which skinning shrinks the volume around the point below
            `min_volume_ratio` (only for points on a grid; None otherwise).
    """

    seen: torch.Tensor
    inside: torch.Tensor
    collapsed: torch.Tensor | None


def volume_ratio(x_world: torch.Tensor, shape: tuple[int, int, int], spacing: list[float]) -> torch.Tensor:
    """det of the skinning map's Jacobian at every point of a canonical grid, by central differences.

    Args:
        x_world: (D*H*W, 3) where the grid's points land.
        shape: (D, H, W) of the grid; spacing: meters along (D, H, W) as `grid_spacing`.
    Returns:
        (D*H*W,) posed volume / canonical volume (1 for a rigid motion, ~0 where space is crushed).
    """
    grid = x_world.reshape(*shape, 3).double()
    # d x_world / d (z, y, x); the columns in (x, y, z) order make the determinant's sign that of the map.
    dz, dy, dx = torch.gradient(grid, spacing=spacing, dim=(0, 1, 2))
    return torch.linalg.det(torch.stack((dx, dy, dz), dim=-1)).reshape(-1)


@torch.no_grad()
def vote_masks(
    points_canonical: torch.Tensor,
    skin: SkinFn,
    views: MaskViews,
    mask_dilation_px: int = 2,
    chunk_size: int = 262144,
    grid: tuple[tuple[int, int, int], list[float]] | None = None,
    min_volume_ratio: float = 0.3,
) -> MaskVotes:
    """Count, for every canonical point, the views that see it and those whose mask holds it.

    Args:
        points_canonical: (P, 3) canonical points (CPU).
        skin: forward skinning into a frame's world space.
        views: the voting masks and cameras.
        mask_dilation_px: masks are dilated by this many pixels first, so that small errors of
            pose, camera or mask do not carve the subject.
        chunk_size: points skinned at once.
        grid: ((D, H, W), spacing) when the points are a `grid_points` grid: then also count the
            views whose skinning crushes the space around each point (see `volume_ratio`).
        min_volume_ratio: below this posed/canonical volume ratio a point counts as crushed.
    """
    kernel = np.ones((2 * mask_dilation_px + 1,) * 2, bool)
    seen = torch.zeros(points_canonical.shape[0], dtype=torch.int32)
    inside = torch.zeros(points_canonical.shape[0], dtype=torch.int32)
    collapsed = torch.zeros(points_canonical.shape[0], dtype=torch.int32) if grid is not None else None
    for mask, K, w2c, frame in zip(views.masks, views.K, views.w2c, views.frames):
        mask = np.asarray(mask, bool)
        if mask_dilation_px > 0:
            mask = ndimage.binary_dilation(mask, structure=kernel)
        height, width = mask.shape
        mask_t = torch.from_numpy(mask)
        K, w2c = torch.as_tensor(np.asarray(K), dtype=torch.float64), torch.as_tensor(np.asarray(w2c), dtype=torch.float64)
        landed = []
        for start in range(0, points_canonical.shape[0], chunk_size):
            x_world = skin(int(frame), points_canonical[start : start + chunk_size]).double().cpu()
            if grid is not None:
                landed.append(x_world.float())
            x_camera = x_world @ w2c[:3, :3].T + w2c[:3, 3]
            depth = x_camera[:, 2]
            uv = (x_camera @ K.T)[:, :2] / depth.clamp_min(1e-6)[:, None]
            u, v = uv[:, 0].round().long(), uv[:, 1].round().long()
            visible = (depth > 1e-6) & (u >= 0) & (u < width) & (v >= 0) & (v < height)
            hit = torch.zeros_like(visible)
            hit[visible] = mask_t[v[visible], u[visible]]
            seen[start : start + chunk_size] += visible.int()
            inside[start : start + chunk_size] += hit.int()
        if grid is not None:
            collapsed += (volume_ratio(torch.cat(landed), *grid) < min_volume_ratio).int()
    return MaskVotes(seen=seen, inside=inside, collapsed=collapsed)


def free_points(seen: torch.Tensor, inside: torch.Tensor, min_outside_fraction: float = 0.1, min_outside: int = 2) -> torch.Tensor:
    """bool, same shape: points that at least max(min_outside, min_outside_fraction * seen) views
    see as background. The fraction tolerates a few views whose mask or pose is off."""
    needed = torch.clamp(torch.ceil(min_outside_fraction * seen.float()), min=float(min_outside)).int()
    return (seen - inside) >= needed


@dataclass(frozen=True)
class HullPrior:
    """The kept part of the visual hull as a closed mesh in canonical space.

    Attributes:
        vertices: (V, 3) float32 canonical vertices.
        faces: (F, 3) int64, normals outwards.
        cell_size: meters between the grid's points.
        views: how many views voted.
        touches_box: the kept region reaches the search box's side (the box may cut the subject).
    """

    vertices: torch.Tensor
    faces: torch.Tensor
    cell_size: float
    views: int
    touches_box: bool


def enclosed_cells(kept: np.ndarray, candidates: np.ndarray) -> np.ndarray:
    """Candidate cells that kept cells enclose within an axis-aligned slice of the grid.

    A cell counts when, in at least one of its three axis-aligned planes, it lies in a hole of the
    kept cells (every path in that plane from it to the grid's edge crosses a kept cell), and all
    six of its neighbours are kept or count too. Under a skirt, the space between the legs is
    walled in on every side in the horizontal plane, while the gap between two bare legs opens to
    the front and back (where the masks carve free space) in every plane, so it stays out. The
    neighbour rule peels one cell off where the added region meets other space: the masks are
    dilated, so the skirt's walls reach a cell below its hem, and the layer they wall in there is
    outside the garment.

    Args:
        kept: (D, H, W) bool cells kept so far.
        candidates: (D, H, W) bool cells that may be added (here: crushed, not free).
    Returns:
        (D, H, W) bool, a subset of `candidates` and disjoint from `kept`.
    """
    holes = np.zeros_like(kept)
    for axis in range(3):
        for k in range(kept.shape[axis]):
            plane = [slice(None)] * 3
            plane[axis] = k
            plane = tuple(plane)
            holes[plane] |= ndimage.binary_fill_holes(kept[plane]) & ~kept[plane]
    added = holes & candidates & ~kept
    six = ndimage.generate_binary_structure(3, 1)
    return added & ndimage.binary_erosion(kept | added, structure=six, border_value=0)


@dataclass(frozen=True)
class HullCells:
    """The hull's rules on a canonical grid, each as a (P,) bool over the grid's points.

    Attributes:
        points: (P, 3) grid points (`grid_points`), the first at the box's minimum corner;
            shape: the grid's (D, H, W); spacing: its cell sizes; cell_size: the size asked for.
        views: how many views voted.
        free: seen as background by a robust number of views.
        crushed: skinning squeezes the space around it in too many views.
        ghost: skinning lands it inside another limb in too many views (all False without a test).
        seen: enough views see it.
        walled_in: crushed cells that `enclosed_cells` gives back (the inside of a skirt).
    """

    points: torch.Tensor
    shape: tuple[int, int, int]
    spacing: list[float]
    cell_size: float
    views: int
    free: torch.Tensor
    crushed: torch.Tensor
    ghost: torch.Tensor
    seen: torch.Tensor
    walled_in: torch.Tensor

    @property
    def kept(self) -> torch.Tensor:
        """(P,) bool: the cells the rules keep."""
        return (~self.free & ~self.crushed & ~self.ghost & self.seen) | self.walled_in


def hull_cells(
    box: torch.Tensor,
    skin: SkinFn,
    views: MaskViews,
    cell_size: float = 0.02,
    mask_dilation_px: int = 2,
    min_outside_fraction: float = 0.1,
    min_seen_fraction: float = 0.5,
    min_volume_ratio: float = 0.3,
    max_collapsed_fraction: float = 0.5,
    ghost_test: GhostTest | None = None,
    max_ghost_fraction: float = 0.5,
) -> HullCells:
    """Apply the hull's rules to a grid over a canonical search box.

    A grid point is kept when it is not free (see `free_points`), at least `min_seen_fraction`
    of the views see it (a point no camera sees is no evidence of the subject), and skinning does
    not crush the space around it in more than `max_collapsed_fraction` of the views. The last
    rule removes folded space: with the legs spread in canonical space and together in every
    frame, blended weights fold the canonical gap between the legs onto the posed legs, inside
    every mask, where no silhouette can carve it; there the posed volume shrinks towards zero,
    while on the body LBS moves space almost rigidly (ratio ~1). Space that rides rigidly into
    another limb is not folded: with `ghost_test`, a point that skinning lands inside another
    limb in more than `max_ghost_fraction` of the views is dropped too (ghost legs beside spread
    canonical legs; igavatar.capture.ghost_limbs). Crushed space that the kept cells enclose in a
    plane is kept after all (`enclosed_cells`): under a skirt the same folding crushes the canonical
    space between the legs, but there it is the inside of the garment, walled in by the skirt, which
    no view can carve or confirm. `hull_prior_mesh` meshes the kept cells.

    Args:
        box: (2, 3) canonical search box (generous: the subject must lie inside).
        skin, views, mask_dilation_px, min_outside_fraction: as `vote_masks` / `free_points`.
        cell_size: grid spacing in meters.
        min_seen_fraction: of the views, how many must see a point for it to count.
        min_volume_ratio, max_collapsed_fraction: the crushed-space rule above.
        ghost_test, max_ghost_fraction: the ghost-limb rule above (None: not tested).
    """
    box = torch.as_tensor(box).detach().float().cpu()
    points, shape = grid_points(box[0], box[1], cell_size)
    spacing = grid_spacing(box[0], box[1], shape)
    votes = vote_masks(points, skin, views, mask_dilation_px, grid=(shape, spacing), min_volume_ratio=min_volume_ratio)
    free = free_points(votes.seen, votes.inside, min_outside_fraction, min_outside=2)
    crushed = votes.collapsed > max_collapsed_fraction * len(views.frames)
    seen = votes.seen >= max(1, math.ceil(min_seen_fraction * len(views.frames)))
    ghost = torch.zeros_like(free)
    if ghost_test is not None:
        candidates = torch.nonzero(~free & seen).squeeze(1)  # crushed ones too: they may be walled in
        x_canonical = points[candidates]
        misplaced = misplaced_votes(x_canonical, ghost_test.weights(x_canonical), skin, views.frames, ghost_test.bones)
        ghost[candidates[misplaced > max_ghost_fraction * len(views.frames)]] = True
    kept = (~free & ~crushed & ~ghost & seen).reshape(shape).numpy()
    walled_in = enclosed_cells(kept, (crushed & ~free & ~ghost & seen).reshape(shape).numpy())
    return HullCells(points=points, shape=shape, spacing=spacing, cell_size=float(cell_size), views=len(views.frames),
                     free=free, crushed=crushed, ghost=ghost, seen=seen, walled_in=torch.from_numpy(walled_in.reshape(-1)))


def hull_prior_mesh(cells: HullCells) -> HullPrior | None:
    """Mesh the hull's kept cells (`hull_cells`); None if nothing is kept.

    Of the kept cells the largest connected part is meshed, its inner cavities filled, after a
    slight blur so that the surface is not staircased at the grid's cells.
    """
    from skimage.measure import marching_cubes

    spacing = cells.spacing
    kept = cells.kept.reshape(cells.shape).numpy()
    labels, count = ndimage.label(kept)
    if count == 0:
        return None
    sizes = ndimage.sum_labels(kept, labels, index=np.arange(1, count + 1))
    kept = ndimage.binary_fill_holes(labels == (int(np.argmax(sizes)) + 1))
    touches = bool(kept[[0, -1]].any() or kept[:, [0, -1]].any() or kept[:, :, [0, -1]].any())
    # Zero padding closes the surface where the region touches the box; the blur rounds the cells.
    volume = ndimage.gaussian_filter(np.pad(kept.astype(np.float32), 1), sigma=0.7)
    # Outward normals: the volume is high inside, which flips skimage's winding ('ascent'), and
    # reading its (z, y, x) axes as (x, y, z) below is a mirror, which flips it back: 'descent'.
    vertices_zyx, faces, _, _ = marching_cubes(volume, level=0.5, spacing=tuple(spacing), gradient_direction="descent")
    vertices = vertices_zyx[:, ::-1] - np.asarray(spacing[::-1]) + cells.points[0].numpy()  # (z, y, x) -> (x, y, z), undo the pad
    faces = faces.astype(np.int64)
    return HullPrior(
        vertices=torch.from_numpy(np.ascontiguousarray(vertices, np.float32)), faces=torch.from_numpy(faces),
        cell_size=cells.cell_size, views=cells.views, touches_box=touches,
    )


def grid_skin(weights_grid: torch.Tensor, box_min: torch.Tensor, box_max: torch.Tensor, bone_transforms: torch.Tensor) -> SkinFn:
    """Forward LBS through a skinning-weight grid, as a SkinFn.

    Args:
        weights_grid: (J, D, H, W) weights over [box_min, box_max].
        bone_transforms: (N, J, 4, 4) canonical -> posed world, per frame.
    """
    from igavatar.skinning.grid import apply_affine, blended_transform_grid, sample_blended_transforms

    cache: dict[int, torch.Tensor] = {}  # the current frame's blended grid, reused over its chunks

    def skin(frame: int, x_canonical: torch.Tensor) -> torch.Tensor:
        if frame not in cache:
            cache.clear()
            cache[frame] = blended_transform_grid(weights_grid.float(), bone_transforms[frame].float())
        return apply_affine(sample_blended_transforms(cache[frame], box_min, box_max, x_canonical.float()), x_canonical.float())

    return skin


def search_box(joints_canonical: torch.Tensor, margin_m: float = 0.35, min_half_m: float = 1.1) -> torch.Tensor:
    """(2, 3) canonical box in which to look for a subject known only by its joints.

    The joints' box grown by `margin_m` (crown, hands and feet lie beyond their joints), and at
    least `min_half_m` either side of the joints' center on every axis, so that a skeleton of one
    joint (a static subject) still gets room for a whole standing person.
    """
    joints = torch.as_tensor(joints_canonical).float()
    lo, hi = joints.amin(0) - margin_m, joints.amax(0) + margin_m
    center = (joints.amin(0) + joints.amax(0)) / 2
    return torch.stack((torch.minimum(lo, center - min_half_m), torch.maximum(hi, center + min_half_m)))
