"""How far a glTF viewer's sparse (top-k) linear blend skinning lands from igavatar's own posing.

    sets = sparse_weight_sets(skin_weights)        # once per mesh: {4: (joints, weights), 8: ...}
    drift = skin_drift_mm(vertices, sets, bone_transforms, reference)   # per frame
    # {"4": {"max": 3.1, "mean": 0.4}, "8": {"max": 1.2, "mean": 0.1}}

A GLB keeps the k largest skinning weights per vertex (renormalized) and no non-rigid offset,
while igavatar poses a canonical vertex with every weight of the skinning grid plus the
pose-conditioned offset. The reference is igavatar's posed vertices of the same frame, so the
numbers are what a user sees as the difference between a viewer and `igavatar export --pose`.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from igavatar.mesh.gltf import top_k_weights


def lbs_sparse(vertices: np.ndarray, joints: np.ndarray, weights: np.ndarray, transforms: torch.Tensor | np.ndarray
               ) -> np.ndarray:
    """LBS with sparse weights, as a glTF viewer skins.

    Args:
        vertices: (V, 3) canonical positions.
        joints: (V, k) joint indices; weights: (V, k) their weights.
        transforms: (J, 4, 4) bone transforms (canonical -> posed world).
    Returns:
        (V, 3) posed vertices, float64.
    """
    b = transforms.double().cpu().numpy() if isinstance(transforms, torch.Tensor) else np.asarray(transforms, np.float64)
    b = b[:, :3, :]  # (J, 3, 4)
    blended = np.einsum("vk,vkrc->vrc", np.asarray(weights, np.float64), b[joints])  # (V, 3, 4)
    return np.einsum("vrc,vc->vr", blended[:, :, :3], np.asarray(vertices, np.float64)) + blended[:, :, 3]


def sparse_weight_sets(skin_weights: np.ndarray, influences: Sequence[int] = (4, 8)
                       ) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """The top-k weights (as the GLB stores them) of each k: {k: (joints (V, k), weights (V, k))}."""
    return {k: top_k_weights(skin_weights, k) for k in influences}


def skin_drift_mm(
    vertices: np.ndarray,
    sets: dict[int, tuple[np.ndarray, np.ndarray]],
    transforms: torch.Tensor | np.ndarray,
    reference: np.ndarray,
) -> dict[str, dict[str, float]]:
    """Per-vertex distance (mm) between top-k LBS and a reference posing of the same vertices.

    Args:
        vertices: (V, 3) canonical positions.
        sets: `sparse_weight_sets` of the vertices' skinning weights.
        transforms: (J, 4, 4) the frame's bone transforms.
        reference: (V, 3) igavatar's posed positions of the same vertices (same frame).
    Returns:
        {str(k): {"max": mm, "mean": mm}} for each k of `sets`.
    """
    result = {}
    for k, (joints, weights) in sets.items():
        gap = np.linalg.norm(lbs_sparse(vertices, joints, weights, transforms) - reference, axis=1) * 1e3
        result[str(k)] = {"max": float(gap.max()), "mean": float(gap.mean())}
    return result
