"""The mesh of the default GLB: the canonical mesh decimated to a size game engines and browsers
load quickly, with its measured distance from the full-resolution mesh.

    vertices, faces, record = engine_mesh(full_vertices, full_faces, target_faces=50_000)
    record["deviation_mm"]   # {"max": ..., "mean": ...}: sampled two-way surface distance

Marching cubes at the paper's 512 gives ~220k faces (17.8 MB as a rigged GLB); a humanoid asset for
an engine has 10-60k. Quadric edge collapse (pymeshlab, as `clean_mesh`) keeps the silhouette and
the limbs; the PLY/OBJ stay at full resolution for measurement and editing.
"""

from __future__ import annotations

import numpy as np
import trimesh

from igavatar.geometry.mesh_ops import nearest_sample_distance
from igavatar.mesh.cleanup import clean_mesh

#: Default face budget of canonical.glb (`export --glb-faces`).
DEFAULT_GLB_FACES = 50_000


def engine_mesh(vertices: np.ndarray, faces: np.ndarray, target_faces: int | None,
                samples: int = 100_000, seed: int = 0) -> tuple[np.ndarray, np.ndarray, dict]:
    """The mesh decimated to at most `target_faces` (None or 0: unchanged), and its record.

    Args:
        vertices (V, 3), faces (F, 3): the cleaned full-resolution mesh.
        target_faces: face budget; a mesh already within it is returned as it is.
        samples: surface points sampled on each mesh for the deviation.
    Returns:
        vertices (V', 3) float32, faces (F', 3) int64, and {"faces", "vertices", "full_faces",
        "decimated", "target_faces", "deviation_mm": {"max", "mean"}}.
    """
    full_faces = int(faces.shape[0])
    if not target_faces or full_faces <= target_faces:
        record = {"faces": full_faces, "vertices": int(vertices.shape[0]), "full_faces": full_faces,
                  "decimated": False, "target_faces": target_faces or None, "deviation_mm": {"max": 0.0, "mean": 0.0}}
        return np.asarray(vertices, np.float32), np.asarray(faces, np.int64), record
    small_v, small_f, _ = clean_mesh(vertices, faces, keep_largest=False, target_faces=target_faces)
    deviation = surface_deviation_mm((vertices, faces), (small_v, small_f), samples, seed)
    record = {"faces": int(small_f.shape[0]), "vertices": int(small_v.shape[0]), "full_faces": full_faces,
              "decimated": True, "target_faces": int(target_faces), "deviation_mm": deviation}
    return small_v, small_f, record


def surface_deviation_mm(a: tuple[np.ndarray, np.ndarray], b: tuple[np.ndarray, np.ndarray], samples: int,
                         seed: int = 0) -> dict[str, float]:
    """Two-way distance between two surfaces, in mm: `samples` points on each, to the nearest of
    4 x `samples` points on the other. Max over both directions (a sampled Hausdorff distance)
    and the mean of the two means."""
    points = [trimesh.sample.sample_surface(trimesh.Trimesh(v, f, process=False), n, seed=seed + k)[0]
              for k, (v, f) in enumerate((a, b)) for n in (samples, 4 * samples)]
    a_to_b = nearest_sample_distance(points[3], points[0])
    b_to_a = nearest_sample_distance(points[1], points[2])
    return {"max": float(max(a_to_b.max(), b_to_a.max()) * 1e3),
            "mean": float(0.5 * (a_to_b.mean() + b_to_a.mean()) * 1e3)}
