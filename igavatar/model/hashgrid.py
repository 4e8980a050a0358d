"""Instant-NGP multiresolution hash encoding with a closed-form spatial Jacobian: C++ fast path + PyTorch reference.

    grid = HashGridEncoding(HashGridConfig(), box_min=torch.tensor([-1.0] * 3), box_max=torch.ones(3))
    features, jacobian = grid.forward_with_jacobian(x_canonical)  # (P, 32), (P, 32, 3)

Points are given in the canonical frame, clamped into the axis-aligned box ``[box_min, box_max]`` and
normalized to ``[0, 1]^3``. Level ``l`` has a grid of ``N_l`` cells per axis (``N_l + 1`` vertices);
its features are the trilinear interpolation of the 8 vertex features around a point. Coarse levels
whose ``(N_l + 1)^3`` vertices fit into the table are indexed densely (no collisions); finer levels
use the Instant-NGP spatial hash ``(i * 1) ^ (j * 2654435761) ^ (k * 805459861) mod T``.

All levels live in one parameter ``table (sum_l T_l, F)`` so that one ``index_select`` with int64
indices gathers every corner of every level and autograd accumulates the table gradient with one
scatter-add (int32 indices make that ~6x slower on CPU). Index arithmetic runs per axis in int32;
hash products wrap modulo 2^32 exactly like tiny-cuda-nn's uint32 ones and are masked with
``& (T - 1)`` before the 8 corners are combined, so only the final row index is int64. All
intermediates keep the point axis innermost (layout ``(..., L, P)``) so elementwise ops vectorise,
and the interpolation is three nested lerps whose differences are the Jacobian's ingredients.
Without autograd, points are processed in chunks of ``HashGridConfig.chunk_size``.

``forward_with_jacobian`` returns ``d features / d x_canonical`` in closed form from the derivative of
the trilinear weights. It is built from ordinary differentiable tensor operations on the gathered
corner features, so the gradient of any loss on the Jacobian (e.g. an eikonal loss) flows into the
table without a double backward through the encoding. ``hashgrid_reference`` is a loop-per-level,
loop-per-corner implementation used by the tests as the ground truth.

Two implementations of one encoding: for a float32 table and float32 points on the CPU, ``_encode``
runs the C++/OpenMP kernel ``igavatar/kernels/csrc/hashgrid.cpp`` (features, Jacobian and their
backward in closed form, wrapped in the autograd function ``_HashGridKernel``; compiled on first use
by :func:`igavatar.kernels.load_kernel`). Every other case (float64, CUDA, kernels disabled with
``IGAVATAR_KERNELS=0`` or unbuildable) runs ``_encode_reference``, the vectorised PyTorch code
described above, which the kernel matches to float32 rounding. The kernel's backward is
``once_differentiable``: a loss on the Jacobian trains the table and the points with one backward,
but a double backward through the encoding needs the reference (float64).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import nn

from igavatar import kernels
from igavatar.errors import InputError
from igavatar.geometry.boxes import check_box

# Instant-NGP / tiny-cuda-nn spatial-hash primes for the x, y, z axes.
HASH_PRIMES: tuple[int, int, int] = (1, 2654435761, 805459861)


@dataclass(frozen=True)
class HashGridConfig:
    """Hyper-parameters of the multiresolution hash encoding (the box is given to the module)."""

    n_levels: int = 16
    """Number of resolution levels L; the output has L * n_features_per_level channels."""

    n_features_per_level: int = 2
    """Feature channels F stored per grid vertex and level."""

    log2_hashmap_size: int = 19
    """log2 of the maximum number of table rows T per level; levels with more vertices are hashed."""

    base_resolution: int = 16
    """Cells per axis N_0 of the coarsest level."""

    finest_resolution: int = 2048
    """Cells per axis N_{L-1} of the finest level; levels grow by the constant factor
    b = (finest / base)^(1 / (L - 1)) and N_l = floor(base * b^l) (Instant-NGP Eq. 2-3)."""

    chunk_size: int = 1 << 14
    """Points per chunk when no gradient is recorded (inference, mesh extraction): keeps the
    (P, L, 8) intermediates cache-sized and the memory bounded for any number of points."""

    grad_chunk_size: int = 1 << 18
    """Points per chunk when autograd records the encoding. Larger than ``chunk_size`` because
    every chunk's backward materialises a dense table gradient (sum_l T_l, F) and adds it up."""

    def __post_init__(self) -> None:
        checks = [
            ("n_levels", self.n_levels >= 1, "must be >= 1"),
            ("n_features_per_level", self.n_features_per_level >= 1, "must be >= 1"),
            ("log2_hashmap_size", 4 <= self.log2_hashmap_size <= 30, "must be in [4, 30]"),
            ("base_resolution", self.base_resolution >= 1, "must be >= 1"),
            (
                "finest_resolution",
                self.finest_resolution >= self.base_resolution,
                f"must be >= base_resolution ({self.base_resolution})",
            ),
            ("finest_resolution", self.finest_resolution <= 1 << 20, "must be <= 2^20"),
            ("chunk_size", self.chunk_size >= 1, "must be >= 1"),
            ("grad_chunk_size", self.grad_chunk_size >= 1, "must be >= 1"),
        ]
        for name, ok, why in checks:
            if not ok:
                raise InputError(f"HashGridConfig.{name}: {getattr(self, name)!r} {why}")

    @property
    def output_dim(self) -> int:
        """Channels of the encoding output, L * F."""
        return self.n_levels * self.n_features_per_level

    @property
    def hashmap_size(self) -> int:
        """Maximum number of table rows per level, T = 2^log2_hashmap_size."""
        return 1 << self.log2_hashmap_size

    def level_resolutions(self) -> list[int]:
        """Cells per axis of every level, ``[N_0, ..., N_{L-1}]``, from base to finest."""
        if self.n_levels == 1:
            return [self.base_resolution]
        log_scale = (math.log(self.finest_resolution) - math.log(self.base_resolution)) / (self.n_levels - 1)
        # The epsilon keeps floor() from dropping the last level to finest - 1 through rounding.
        return [int(math.floor(self.base_resolution * math.exp(l * log_scale) + 1e-6)) for l in range(self.n_levels)]

    def level_is_dense(self) -> list[bool]:
        """Whether each level is indexed densely, i.e. its (N_l + 1)^3 vertices fit into T rows."""
        return [(n + 1) ** 3 <= self.hashmap_size for n in self.level_resolutions()]

    def level_table_sizes(self) -> list[int]:
        """Table rows of every level: (N_l + 1)^3 for dense levels, T for hashed ones."""
        return [(n + 1) ** 3 if dense else self.hashmap_size
                for n, dense in zip(self.level_resolutions(), self.level_is_dense())]


class HashGridEncoding(nn.Module):
    """Multiresolution hash encoding of canonical points, output ``(P, L * F)``, level-major.

    Parameters: ``table (sum_l T_l, F)``, all levels stacked (``level_offsets`` gives the first row
    of each level); initialized uniformly in ``[-1e-4, 1e-4]``. Buffers ``box_min``, ``box_max`` (3,).
    """

    def __init__(self, config: HashGridConfig, box_min: torch.Tensor, box_max: torch.Tensor) -> None:
        super().__init__()
        self.config = config
        box_min = torch.as_tensor(box_min, dtype=torch.float32)
        box_max = torch.as_tensor(box_max, dtype=torch.float32)
        check_box(box_min, box_max, "hash grid box")
        self.register_buffer("box_min", box_min.clone())
        self.register_buffer("box_max", box_max.clone())

        resolutions = config.level_resolutions()
        dense = config.level_is_dense()
        sizes = config.level_table_sizes()
        # Resolutions never decrease, so the dense levels are exactly the first n_dense_levels.
        self.n_dense_levels = sum(dense)
        self.level_sizes = sizes
        # Storage: hashed levels first, each starting at a multiple of T (the index fold relies on
        # it), then the dense levels; ``level_offsets`` maps a level to its first row.
        n_hashed = config.n_levels - self.n_dense_levels
        offsets = [0] * config.n_levels
        row = n_hashed * config.hashmap_size
        for level in range(self.n_dense_levels):
            offsets[level] = row
            row += sizes[level]
        for k in range(n_hashed):
            offsets[self.n_dense_levels + k] = k * config.hashmap_size

        self.table = nn.Parameter(torch.empty(sum(sizes), config.n_features_per_level))
        nn.init.uniform_(self.table, -1e-4, 1e-4)

        # Per-level, per-axis integer multipliers. Dense: row-major strides (1, N+1, (N+1)^2), corner
        # index = sum over axes. Hashed: primes, corner index = XOR over axes of (coord * prime) & (T-1)
        # (masking per axis equals masking the XOR since & distributes over ^).
        multipliers = []
        for n, is_dense in zip(resolutions, dense):
            multipliers.append([1, n + 1, (n + 1) ** 2] if is_dense else list(HASH_PRIMES))
        self.register_buffer("_resolution", torch.tensor(resolutions, dtype=torch.float32), persistent=False)
        self.register_buffer("_resolution_int", torch.tensor(resolutions, dtype=torch.int32), persistent=False)
        # int32 with two's-complement wrap: 2654435761 is stored as 2654435761 - 2^32.
        wrapped = [[m - (1 << 32) if m >= 1 << 31 else m for m in row] for row in multipliers]
        self.register_buffer("_multiplier", torch.tensor(wrapped, dtype=torch.int32), persistent=False)
        self.register_buffer("_offset", torch.tensor(offsets, dtype=torch.int64), persistent=False)

    @property
    def output_dim(self) -> int:
        """Channels of the output, L * F."""
        return self.config.output_dim

    @property
    def level_offsets(self) -> list[int]:
        """First table row of every level."""
        return self._offset.tolist()

    def level_tables(self) -> list[torch.Tensor]:
        """Views ``(T_l, F)`` of the table in level order (they share storage and autograd with it)."""
        return [self.table[offset:offset + size] for offset, size in zip(self.level_offsets, self.level_sizes)]

    def forward(self, x_canonical: torch.Tensor) -> torch.Tensor:
        """Encode canonical points ``x_canonical (P, 3)`` -> features ``(P, L * F)``."""
        chunks = [self._encode(x, with_jacobian=False)[0] for x in self._split(x_canonical)]
        return chunks[0] if len(chunks) == 1 else torch.cat(chunks, dim=0)

    def forward_with_jacobian(self, x_canonical: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Encode ``x_canonical (P, 3)`` -> ``(features (P, C), d features / d x_canonical (P, C, 3))``.

        C = L * F. The Jacobian is exact (closed form) inside the grid cells and zero along axes on
        which the point lies outside the box (the clamp is flat there). Both outputs are
        differentiable wrt the table and wrt ``x_canonical``.
        """
        chunks = [self._encode(x, with_jacobian=True) for x in self._split(x_canonical)]
        if len(chunks) == 1:
            return chunks[0]  # type: ignore[return-value]
        return torch.cat([c[0] for c in chunks]), torch.cat([c[1] for c in chunks])  # type: ignore[misc]

    def _split(self, x_canonical: torch.Tensor) -> tuple[torch.Tensor, ...]:
        if x_canonical.ndim != 2 or x_canonical.shape[-1] != 3:
            raise ValueError(f"HashGridEncoding: x_canonical must have shape (P, 3), got {tuple(x_canonical.shape)}")
        if not x_canonical.is_floating_point():
            raise TypeError(f"HashGridEncoding: x_canonical must be floating point, got {x_canonical.dtype}")
        recording = torch.is_grad_enabled() and (self.table.requires_grad or x_canonical.requires_grad)
        return x_canonical.split(self.config.grad_chunk_size if recording else self.config.chunk_size)

    def _encode(self, x_canonical: torch.Tensor, with_jacobian: bool) -> tuple[torch.Tensor, torch.Tensor | None]:
        """One chunk: the C++ kernel for float32 CPU table and points when it loads, else the reference."""
        table = self.table
        if (
            table.dtype == torch.float32 and x_canonical.dtype == torch.float32
            and table.device.type == "cpu" and x_canonical.device.type == "cpu"
        ):
            kernel = kernels.load_kernel("hashgrid")  # lazy: compiled/loaded on first use
            if kernel is not None:
                return self._encode_kernel(kernel, x_canonical, with_jacobian)
        return self._encode_reference(x_canonical, with_jacobian)

    def _encode_kernel(
        self, kernel, x_canonical: torch.Tensor, with_jacobian: bool
    ) -> tuple[torch.Tensor, torch.Tensor | None]:
        grid = _KernelGrid(
            kernel=kernel,
            offsets=self._offset,
            resolutions=self._resolution_int,
            multipliers=self._multiplier,
            n_dense=self.n_dense_levels,
            hashmap_size=self.config.hashmap_size,
            box_min=self.box_min.to(torch.float32).contiguous(),
            box_max=self.box_max.to(torch.float32).contiguous(),
        )
        features, jacobian = _HashGridKernel.apply(x_canonical, self.table, grid, with_jacobian)
        return features, (jacobian if with_jacobian else None)

    def _encode_reference(
        self, x_canonical: torch.Tensor, with_jacobian: bool
    ) -> tuple[torch.Tensor, torch.Tensor | None]:
        """One chunk in PyTorch ops (any dtype/device): the semantics the C++ kernel reproduces."""
        # Layout: every intermediate is (..., L, P) or (..., L * P * F) with the point axis innermost
        # and contiguous, so each elementwise op is one long vectorised loop. Broadcasting over small
        # inner axes (the 2 corners of an axis, the F features) was ~6x slower on CPU.
        cfg = self.config
        n_points, n_levels, n_feat = x_canonical.shape[0], cfg.n_levels, cfg.n_features_per_level
        n_dense = self.n_dense_levels
        dtype = self.table.dtype
        box_min = self.box_min.to(dtype)
        extent = self.box_max.to(dtype) - box_min
        resolution = self._resolution.to(dtype)[None, :, None]  # (1, L, 1)
        x = x_canonical.to(dtype)

        u = ((x - box_min) / extent).clamp(0.0, 1.0)  # (P, 3) in the unit cube
        pos = u.t()[:, None, :] * resolution  # (3, L, P) in cell units
        # The last vertex belongs to the last cell (frac = 1) so corner + 1 stays inside the grid.
        cell = torch.minimum(pos.detach().floor().to(torch.int32), self._resolution_int[None, :, None] - 1)
        frac = pos - cell.to(dtype)  # (3, L, P), differentiable wrt x through pos

        # Row-index contribution of the lower / upper corner along each axis: (3, 2, L, P), int32.
        # Hashed products wrap modulo 2^32 like tiny-cuda-nn's uint32 arithmetic; only the low bits
        # survive "& (T - 1)", and they are the same for the wrapped and the exact product.
        multiplier = self._multiplier.t()[:, :, None]  # (3, L, 1)
        code_lower = cell * multiplier
        code = torch.stack((code_lower, code_lower + multiplier), dim=1)
        code[:, :, n_dense:] &= cfg.hashmap_size - 1
        cx, cy = code[0], code[1]  # (2, L, P)
        # Fold each level's first table row into the z code (int64: the table may exceed 2^31 rows).
        # Hashed levels start at multiples of T and their codes are < T, so
        # "offset + (a ^ b ^ c)" equals "a ^ b ^ (c + offset)".
        cz = code[2].long() + self._offset[None, :, None]
        # Rows of the 8 corners (dx, dy, dz, L, P).
        index = torch.empty(2, 2, 2, n_levels, n_points, dtype=torch.int64, device=x.device)
        if n_dense > 0:
            cxy = cx[:, None, :n_dense] + cy[None, :, :n_dense]
            torch.add(cxy[:, :, None], cz[None, None, :, :n_dense], out=index[:, :, :, :n_dense])
        if n_dense < n_levels:
            cxy = cx[:, None, n_dense:] ^ cy[None, :, n_dense:]
            torch.bitwise_xor(cxy[:, :, None], cz[None, None, :, n_dense:], out=index[:, :, :, n_dense:])

        # Corner features flattened to (dx, dy, dz, L * P * F); the fractions repeated over F to match.
        size = n_levels * n_points * n_feat
        corner = torch.index_select(self.table, 0, index.view(-1)).view(4, 2, size)  # (dx dy, dz, S)
        tx, ty, tz = frac[..., None].expand(3, n_levels, n_points, n_feat).reshape(3, size).unbind(0)
        # Trilinear interpolation as three nested lerps (z, then y, then x); the differences along
        # each axis are the partial derivatives wrt the fractions, reused by the Jacobian. Slices are
        # taken with unbind: its backward is one stack, where indexing/select would zero-fill a full
        # copy of the input per slice.
        corner_z0, corner_z1 = corner.unbind(1)
        diff_z = corner_z1 - corner_z0  # (4, S), rows (dx, dy)
        lerp_y0, lerp_y1 = torch.addcmul(corner_z0, tz, diff_z).view(2, 2, size).unbind(1)
        diff_yz = lerp_y1 - lerp_y0  # (2, S), rows dx
        lerp_x0, lerp_x1 = torch.addcmul(lerp_y0, ty, diff_yz).unbind(0)
        diff_xyz = lerp_x1 - lerp_x0  # (S,)
        value = torch.addcmul(lerp_x0, tx, diff_xyz)
        features = value.view(n_levels, n_points, n_feat).transpose(0, 1).reshape(n_points, cfg.output_dim)
        if not with_jacobian:
            return features, None

        # d frac / d x = N_l / extent inside the box, 0 on axes where the clamp is active.
        inside = ((x >= box_min) & (x <= box_min + extent)).to(dtype)  # (P, 3)
        dfrac_dx = (inside / extent).t()[:, None, :] * resolution  # (3, L, P)
        sx, sy, sz = dfrac_dx[..., None].expand(3, n_levels, n_points, n_feat).reshape(3, size).unbind(0)
        d_dx = diff_xyz * sx
        diff_y_x0, diff_y_x1 = diff_yz.unbind(0)
        d_dy = torch.addcmul(diff_y_x0, tx, diff_y_x1 - diff_y_x0) * sy
        diff_z_y0, diff_z_y1 = diff_z.view(2, 2, size).unbind(1)
        diff_z_x0, diff_z_x1 = torch.addcmul(diff_z_y0, ty, diff_z_y1 - diff_z_y0).unbind(0)
        d_dz = torch.addcmul(diff_z_x0, tx, diff_z_x1 - diff_z_x0) * sz
        jacobian = torch.stack((d_dx, d_dy, d_dz)).view(3, n_levels, n_points, n_feat)
        jacobian = jacobian.permute(2, 1, 3, 0).reshape(n_points, cfg.output_dim, 3)
        return features, jacobian


@dataclass(frozen=True)
class _KernelGrid:
    """Everything the C++ kernel needs besides the points and the table (constants: no gradient)."""

    kernel: object
    offsets: torch.Tensor
    resolutions: torch.Tensor
    multipliers: torch.Tensor
    n_dense: int
    hashmap_size: int
    box_min: torch.Tensor
    box_max: torch.Tensor

    def args(self) -> tuple:
        return (self.offsets, self.resolutions, self.multipliers, self.n_dense, self.hashmap_size,
                self.box_min, self.box_max)


class _HashGridKernel(torch.autograd.Function):
    """``(x (P, 3), table (R, F)) -> (features (P, C), jacobian (P, C, 3) or empty)`` via the C++ kernel."""

    @staticmethod
    def forward(ctx, x: torch.Tensor, table: torch.Tensor, grid: _KernelGrid, with_jacobian: bool):
        x = x.contiguous()
        table = table.contiguous()
        features, jacobian = grid.kernel.forward(x, table, *grid.args(), with_jacobian)
        ctx.save_for_backward(x, table)
        ctx.grid = grid
        ctx.set_materialize_grads(False)
        if not with_jacobian:
            ctx.mark_non_differentiable(jacobian)
        return features, jacobian

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_features: torch.Tensor | None, grad_jacobian: torch.Tensor | None):
        need_x, need_table = ctx.needs_input_grad[0], ctx.needs_input_grad[1]
        if (grad_features is None and grad_jacobian is None) or not (need_x or need_table):
            return None, None, None, None
        x, table = ctx.saved_tensors
        empty = x.new_empty(0)
        grad_features = empty if grad_features is None else grad_features.contiguous()
        grad_jacobian = empty if grad_jacobian is None or grad_jacobian.numel() == 0 else grad_jacobian.contiguous()
        grad_table, grad_x = ctx.grid.kernel.backward(
            grad_features, grad_jacobian, x, table, *ctx.grid.args(), need_x, need_table
        )
        return (grad_x if need_x else None), (grad_table if need_table else None), None, None


def hashgrid_reference(
    x_canonical: torch.Tensor,
    tables: list[torch.Tensor],
    config: HashGridConfig,
    box: tuple[torch.Tensor, torch.Tensor],
) -> torch.Tensor:
    """Naive multiresolution hash encoding: loops over levels and the 8 corners, for tests.

    x_canonical (P, 3); tables: one ``(T_l, F)`` tensor per level (``HashGridEncoding.level_tables()``);
    box = (box_min (3,), box_max (3,)). Returns features (P, L * F), differentiable wrt x and tables.
    Hashing is done in exact int64 arithmetic followed by ``% 2^32 % T`` (uint32 semantics).
    """
    box_min, box_max = (torch.as_tensor(b, dtype=x_canonical.dtype, device=x_canonical.device) for b in box)
    u = ((x_canonical - box_min) / (box_max - box_min)).clamp(0.0, 1.0)
    hashmap_size = 1 << config.log2_hashmap_size
    outputs = []
    for level, n in enumerate(config.level_resolutions()):
        table = tables[level]
        pos = u * n
        cell = pos.detach().floor().long().clamp(max=n - 1)
        frac = pos - cell.to(pos.dtype)
        feature = torch.zeros(x_canonical.shape[0], table.shape[1], dtype=table.dtype, device=table.device)
        for dx in (0, 1):
            for dy in (0, 1):
                for dz in (0, 1):
                    i = cell[:, 0] + dx
                    j = cell[:, 1] + dy
                    k = cell[:, 2] + dz
                    if (n + 1) ** 3 <= hashmap_size:
                        row = i + j * (n + 1) + k * (n + 1) ** 2
                    else:
                        row = ((i * HASH_PRIMES[0]) ^ (j * HASH_PRIMES[1]) ^ (k * HASH_PRIMES[2])) % (1 << 32)
                        row = row % hashmap_size
                    wx = frac[:, 0] if dx else 1.0 - frac[:, 0]
                    wy = frac[:, 1] if dy else 1.0 - frac[:, 1]
                    wz = frac[:, 2] if dz else 1.0 - frac[:, 2]
                    feature = feature + (wx * wy * wz)[:, None] * table[row]
        outputs.append(feature)
    return torch.cat(outputs, dim=1)
