"""Triangle-mesh helpers on (V, 3) vertex and (F, 3) face arrays: normals, connected components.

    normals = vertex_normals(vertices, faces)           # (V, 3) float32 unit, area-weighted
    labels = connected_components(len(vertices), faces) # (F,) 0 = the largest component
    kept, faces = largest_component(faces, len(vertices))
    distance = nearest_sample_distance(surface_samples, points)  # (P,)
"""

from __future__ import annotations

import numpy as np
import scipy.sparse
import scipy.sparse.csgraph
from scipy.spatial import cKDTree

from igavatar.interrupts import deferred_interrupts


def connected_components(num_vertices: int, faces: np.ndarray) -> np.ndarray:
    """Component label (F,) int64 of every face; faces sharing a vertex share a component.

    Labels are ordered by decreasing face count (0 = the largest component).
    """
    if faces.shape[0] == 0:
        return np.zeros(0, dtype=np.int64)
    rows = np.concatenate((faces[:, 0], faces[:, 1]))
    cols = np.concatenate((faces[:, 1], faces[:, 2]))
    graph = scipy.sparse.coo_matrix(
        (np.ones(rows.shape[0], dtype=np.int8), (rows, cols)), shape=(num_vertices, num_vertices)
    )
    _, vertex_label = scipy.sparse.csgraph.connected_components(graph, directed=False)
    face_label = vertex_label[faces[:, 0]]
    # Relabel by size, largest first (ties by old label, so the result is deterministic).
    sizes = np.bincount(face_label)
    order = np.lexsort((np.arange(sizes.shape[0]), -sizes))
    rank = np.empty_like(order)
    rank[order] = np.arange(order.shape[0])
    return rank[face_label].astype(np.int64)


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Unit area-weighted vertex normals (V, 3) float32; zero for vertices in no (non-degenerate) face."""
    v, f = np.asarray(vertices, np.float64), np.asarray(faces, np.int64)
    # The cross product's length is twice the face area, so summing it weights faces by area.
    face_normals = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    corners = f.reshape(-1)
    normals = np.stack(
        [
            np.bincount(corners, weights=np.repeat(face_normals[:, axis], 3), minlength=v.shape[0])
            for axis in range(3)
        ],
        axis=1,
    )
    length = np.linalg.norm(normals, axis=1, keepdims=True)
    normals = np.divide(normals, length, out=np.zeros_like(normals), where=length > 0)
    return normals.astype(np.float32)


def largest_component(faces: np.ndarray, num_vertices: int) -> tuple[np.ndarray, np.ndarray]:
    """Keep the component with the most faces (drops eyes, teeth and other inner shells).

    Returns:
        kept: (V',) indices of the kept vertices into the input, ascending; faces: (F', 3) the
        component's faces in their original order, re-indexed into the kept vertices.
    """
    faces = np.asarray(faces, np.int64)
    kept_faces = faces[connected_components(num_vertices, faces) == 0]
    kept = np.unique(kept_faces)
    remap = np.full(num_vertices, -1, dtype=np.int64)
    remap[kept] = np.arange(kept.size)
    return kept, remap[kept_faces]


def nearest_sample_distance(samples: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Distance (P,) from each of `points` (P, 3) to its nearest of `samples` (S, 3), exact.

    On every core. Ctrl-C is held until the query ends: scipy returns on an interrupt while its
    worker threads still read the arrays, which crashes the process (igavatar.interrupts).
    The unbalanced, uncompacted tree finds the same neighbours; for points far from the samples
    it is ~7x faster to build and query (8.2 s -> 1.0 s for 200k points on 2 cores).
    """
    with deferred_interrupts():
        distance, _ = cKDTree(samples, balanced_tree=False, compact_nodes=False).query(points, workers=-1)
    return distance
