"""Marching cubes of an SDF callable, coarse-to-fine and narrow-band (METHOD.md section 5).

    vertices, faces = extract_mesh(sdf_fn, box_min, box_max, resolution=512)
    # vertices (V, 3) float32 in sdf_fn's frame, faces (F, 3) int64, normals pointing outwards

Two passes, as in the paper's code: a coarse pass over the whole box finds the tight box of the
surface; the fine pass samples the tight box with cubic voxels, the finest axis getting
`resolution` samples. The fine pass is narrow-band: the fine grid is cut into blocks of
`block_size` cells per edge (neighbours share their boundary samples, so every cell lies inside a
block). A block is evaluated only if the SDF at its center is within `band` x its half-diagonal of
the level (candidates screened first with the trilinearly upsampled coarse pass); any other block
holds no surface if the field is a distance (1-Lipschitz), so it is filled with a large value of
its center's sign. Marching cubes then sees the same sign changes as on the dense grid, and the
mesh is the same (tested). The test assumes |grad sdf| <= ~1; raise `band` for fields far from a
distance (a band of 2 tolerates gradients up to 2).

`sdf_fn` maps x (P, 3) float32 on `device` to sdf (P,) (or (P, 1)), positive outside; it is called
under torch.no_grad() (a field that needs autograd inside must re-enable it). The volume is indexed
[i, j, k] <-> (x, y, z).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import scipy.ndimage
import skimage.measure
import torch

from igavatar.errors import InputError

SdfFn = Callable[[torch.Tensor], torch.Tensor]
ProgressFn = Callable[[int, int], None]


def _cubic_grid(
    box_min: np.ndarray, box_max: np.ndarray, resolution: int
) -> tuple[np.ndarray, float, np.ndarray]:
    """A grid of cubic voxels covering the box, `resolution` samples on its longest axis.

    Returns origin (3,) float64 (the world position of sample [0, 0, 0]), the spacing, and the
    sample counts (3,) int64. Shorter axes get just enough samples to cover their extent and are
    centerd on the box, so they overhang it by less than half a voxel on each side.
    """
    extent = box_max - box_min
    spacing = float(extent.max()) / (resolution - 1)
    counts = np.maximum(np.ceil(extent / spacing - 1e-6).astype(np.int64) + 1, 2)
    covered = (counts - 1) * spacing
    origin = 0.5 * (box_min + box_max) - 0.5 * covered
    return origin, spacing, counts


#: Bytes per fine-grid sample: the float32 SDF volume, the boolean masks made from it and
#: marching cubes' working copy (measured peaks stay below this on a full box).
MARCHING_BYTES_PER_SAMPLE = 8


def marching_cubes_bytes(box_min, box_max, resolution: int) -> int:
    """Memory (a bound) of extracting a mesh at `resolution` inside the box: the full fine grid.

    The narrow band and the tight box usually need less; a size refused by this bound could need
    up to this much when the surface fills the box.
    """
    lo = np.asarray(torch.as_tensor(box_min).detach().cpu(), dtype=np.float64).reshape(-1)
    hi = np.asarray(torch.as_tensor(box_max).detach().cpu(), dtype=np.float64).reshape(-1)
    _, _, counts = _cubic_grid(lo, hi, int(resolution))
    return int(np.prod(counts.astype(np.float64)) * MARCHING_BYTES_PER_SAMPLE)


class _Evaluator:
    """Evaluates sdf_fn at numpy points in chunks, counting evaluations for the progress callback."""

    def __init__(
        self, sdf_fn: SdfFn, chunk_points: int, device: torch.device, progress: ProgressFn | None
    ) -> None:
        self.sdf_fn = sdf_fn
        self.chunk_points = chunk_points
        self.device = device
        self.progress = progress
        self.done = 0
        self.total = 0

    def points(self, x: np.ndarray) -> np.ndarray:
        """sdf (P,) float32 at points x (P, 3), P at most chunk_points."""
        x_torch = torch.from_numpy(np.ascontiguousarray(x, dtype=np.float32)).to(self.device)
        with torch.no_grad():
            sdf = self.sdf_fn(x_torch)
        if not isinstance(sdf, torch.Tensor) or sdf.numel() != x.shape[0]:
            shape = tuple(sdf.shape) if isinstance(sdf, torch.Tensor) else type(sdf).__name__
            raise InputError(
                f"extract_mesh: sdf_fn returned {shape} for {x.shape[0]} points; expected a tensor "
                f"of shape ({x.shape[0]},) or ({x.shape[0]}, 1)"
            )
        values = sdf.detach().reshape(-1).float().cpu().numpy()
        finite = np.isfinite(values)
        if not finite.all():
            raise InputError(
                f"extract_mesh: sdf_fn returned {int((~finite).sum())} NaN or infinite values "
                f"(the first at x = {x[~finite][0].tolist()})"
            )
        self.done += x.shape[0]
        if self.progress is not None:
            self.progress(self.done, self.total)
        return values

    def many_points(self, x: np.ndarray) -> np.ndarray:
        """sdf (P,) at points x (P, 3), any P."""
        return np.concatenate(
            [self.points(x[i : i + self.chunk_points]) for i in range(0, x.shape[0], self.chunk_points)]
            or [np.zeros(0, np.float32)]
        )

    def grid(
        self, volume: np.ndarray, origin: np.ndarray, spacing: float, flat_index: np.ndarray | None
    ) -> None:
        """Write sdf at the samples `flat_index` (K,) of `volume` (nx, ny, nz) (None: all samples)."""
        size = volume.size if flat_index is None else flat_index.shape[0]
        flat_volume = volume.reshape(-1)
        for start in range(0, size, self.chunk_points):
            stop = min(start + self.chunk_points, size)
            chunk = np.arange(start, stop) if flat_index is None else flat_index[start:stop]
            index = np.stack(np.unravel_index(chunk, volume.shape), axis=1)
            flat_volume[chunk] = self.points(origin + index * spacing)


def _surface_cells(volume: np.ndarray, level: float, near: float) -> np.ndarray:
    """(nx-1, ny-1, nz-1) bool: cells whose corners change sign or come within `near` of the level."""
    low = volume - level
    high = low.copy()
    magnitude = np.abs(low)
    for axis in range(3):
        first = [slice(None)] * 3
        second = [slice(None)] * 3
        first[axis], second[axis] = slice(None, -1), slice(1, None)
        low = np.minimum(low[tuple(first)], low[tuple(second)])
        high = np.maximum(high[tuple(first)], high[tuple(second)])
        magnitude = np.minimum(magnitude[tuple(first)], magnitude[tuple(second)])
    return ((low <= 0) & (high >= 0)) | (magnitude < near)


def _narrow_band(
    evaluator: _Evaluator,
    coarse: np.ndarray,
    origin_c: np.ndarray,
    spacing_c: float,
    origin_f: np.ndarray,
    spacing_f: float,
    counts_f: np.ndarray,
    level: float,
    block_size: int,
    band: float,
    far_value: float,
) -> tuple[np.ndarray, np.ndarray]:
    """The fine volume pre-filled with level +- far_value, and the flat indices (K,) to evaluate.

    Block b covers samples [b B, (b+1) B] on each axis (one sample of overlap, so every cell of the
    grid lies inside some block). A block whose center is farther from the surface than `band` x
    its half-diagonal holds no surface for a distance field; it keeps one sign, that of its center.
    Candidates are first screened with the upsampled coarse SDF (whose error is at most one coarse
    cell diagonal for a 1-Lipschitz field), then decided by the SDF at their centers.
    """
    num_blocks = -(-counts_f // block_size)
    blocks = np.stack(np.meshgrid(*(np.arange(n) for n in num_blocks), indexing="ij"), -1).reshape(-1, 3)
    centers = origin_f + (blocks + 0.5) * block_size * spacing_f
    reach = band * 0.5 * math.sqrt(3.0) * block_size * spacing_f
    center_sdf = scipy.ndimage.map_coordinates(
        coarse, ((centers - origin_c) / spacing_c).T, order=1, mode="nearest"
    ) - level
    # Trilinear interpolation of a 1-Lipschitz field errs by at most one coarse cell diagonal;
    # blocks that stick out of the coarse grid (clamped lookups) get one more block diagonal.
    candidate = np.abs(center_sdf) < reach + math.sqrt(3.0) * (spacing_c + block_size * spacing_f)
    evaluator.total += int(candidate.sum())
    center_sdf[candidate] = evaluator.many_points(centers[candidate]) - level
    active = (np.abs(center_sdf) < reach).reshape(tuple(num_blocks))

    # Fill, slab by slab to bound memory, every sample with its block's sign; the active
    # blocks' samples are overwritten by evaluate.
    fill = (level + np.where(center_sdf < 0, -far_value, far_value)).astype(np.float32).reshape(tuple(num_blocks))
    fine = np.empty(tuple(counts_f), dtype=np.float32)
    for bx in range(num_blocks[0]):
        slab = np.repeat(np.repeat(fill[bx], block_size, 0), block_size, 1)
        fine[bx * block_size : (bx + 1) * block_size] = slab[None, : counts_f[1], : counts_f[2]]

    # Samples to evaluate: those of active blocks, plus the first sample after each active block
    # on every axis (the overlap). The overlap is a product of per-axis sets, so OR-ing each
    # block-start plane with the plane before it, axis after axis, covers edges and corners too.
    mask = active
    for axis in range(3):
        mask = np.repeat(mask, block_size, axis=axis)
    for axis in range(3):
        ahead = [slice(None)] * 3
        behind = [slice(None)] * 3
        ahead[axis], behind[axis] = slice(block_size, None, block_size), slice(block_size - 1, -1, block_size)
        mask[tuple(ahead)] |= mask[tuple(behind)]
    mask = mask[: counts_f[0], : counts_f[1], : counts_f[2]]
    return fine, np.flatnonzero(mask)


def extract_mesh(
    sdf_fn: SdfFn,
    box_min: np.ndarray | torch.Tensor,
    box_max: np.ndarray | torch.Tensor,
    resolution: int = 512,
    coarse_resolution: int = 64,
    chunk_points: int = 2**17,
    level: float = 0.0,
    progress: ProgressFn | None = None,
    *,
    narrow_band: bool = True,
    block_size: int = 8,
    band: float = 1.0,
    device: torch.device | str | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Triangle mesh of the level set {sdf = level} inside a box.

    Args:
        sdf_fn: x (P, 3) float32 -> sdf (P,) or (P, 1), positive outside.
        box_min, box_max: (3,) corners of the box to search, in sdf_fn's frame (meters).
        resolution: samples on the longest axis of the fine (tight-box) grid; voxels are cubic.
        coarse_resolution: samples on the longest axis of the coarse grid over the whole box.
        chunk_points: most points per sdf_fn call.
        level: the iso-value.
        progress: optional callback progress(done, total), counted in SDF evaluations; `total`
            grows as each pass is sized (coarse grid, block centers, fine samples).
        narrow_band: evaluate only blocks near the surface in the fine pass (False: every sample
            of the tight box, the reference).
        block_size: fine samples per block edge for the narrow band.
        band: a block is evaluated when |sdf - level| at its center is below band x its
            half-diagonal (1 is exact for a true distance field).
        device: where the points are made; default box_min's device if it is a tensor, else CPU.
    Returns:
        vertices (V, 3) float32 in sdf_fn's frame and faces (F, 3) int64, wound so that normals
        point to positive SDF (outwards). Both are empty ((0, 3)) if the SDF has no level crossing
        in the box.
    """
    if device is None:
        device = box_min.device if isinstance(box_min, torch.Tensor) else torch.device("cpu")
    device = torch.device(device)
    box_lo = np.asarray(torch.as_tensor(box_min).detach().cpu(), dtype=np.float64).reshape(-1)
    box_hi = np.asarray(torch.as_tensor(box_max).detach().cpu(), dtype=np.float64).reshape(-1)
    if box_lo.shape != (3,) or box_hi.shape != (3,):
        raise InputError(
            f"extract_mesh: box_min/box_max have shapes {box_lo.shape}/{box_hi.shape}, expected (3,)"
        )
    if not (np.all(np.isfinite(box_lo)) and np.all(np.isfinite(box_hi)) and np.all(box_hi > box_lo)):
        raise InputError(
            f"extract_mesh: box_min {box_lo.tolist()} must be finite and below box_max "
            f"{box_hi.tolist()} on every axis"
        )
    for name, value, least in (
        ("resolution", resolution, 2), ("coarse_resolution", coarse_resolution, 2),
        ("chunk_points", chunk_points, 1), ("block_size", block_size, 1),
    ):
        if int(value) != value or value < least:
            raise InputError(f"extract_mesh: {name} = {value}, expected an integer >= {least}")

    evaluator = _Evaluator(sdf_fn, int(chunk_points), device, progress)

    # Coarse pass over the whole box.
    origin_c, spacing_c, counts_c = _cubic_grid(box_lo, box_hi, int(coarse_resolution))
    coarse = np.empty(tuple(counts_c), dtype=np.float32)
    evaluator.total = coarse.size
    evaluator.grid(coarse, origin_c, spacing_c, None)
    # A distance field crossing a cell is within one cell diagonal of all its corners.
    cells = np.argwhere(_surface_cells(coarse, level, math.sqrt(3.0) * spacing_c))
    empty = (np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int64))
    if cells.shape[0] == 0:
        return empty

    # The tight box: surface cells padded by two coarse cells, inside the coarse grid.
    pad = 2
    lo = np.maximum(cells.min(axis=0) - pad, 0)
    hi = np.minimum(cells.max(axis=0) + 1 + pad, counts_c - 1)
    origin_f, spacing_f, counts_f = _cubic_grid(
        origin_c + lo * spacing_c, origin_c + hi * spacing_c, int(resolution)
    )

    if narrow_band:
        # Far blocks get a distance from the level that no SDF inside the box reaches.
        far_value = 10.0 * float(np.linalg.norm(box_hi - box_lo))
        fine, flat_index = _narrow_band(
            evaluator, coarse, origin_c, spacing_c, origin_f, spacing_f, counts_f,
            level, int(block_size), float(band), far_value,
        )
        evaluator.total += flat_index.shape[0]
        evaluator.grid(fine, origin_f, spacing_f, flat_index)
    else:
        fine = np.empty(tuple(counts_f), dtype=np.float32)
        evaluator.total += fine.size
        evaluator.grid(fine, origin_f, spacing_f, None)

    # Samples exactly at the level make marching cubes emit zero-area triangles and coincident
    # vertices (288 and 144 on a box SDF with 814 such samples); just outside, they emit neither.
    exact = fine == np.float32(level)
    if exact.any():
        fine[exact] = np.nextafter(np.float32(level), np.float32(np.inf))
    if fine.min() > level or fine.max() < level:
        return empty
    # skimage's default 'descent' winding is the one whose right-hand-rule normals point up the
    # field's gradient (towards positive SDF, outwards); 'ascent' flips it (checked on a sphere).
    vertices, faces, _, _ = skimage.measure.marching_cubes(
        fine, level=level, spacing=(spacing_f,) * 3, gradient_direction="descent"
    )
    vertices = (vertices.astype(np.float64) + origin_f).astype(np.float32)
    return vertices, faces.astype(np.int64)
