"""Every geometry metric of one posed frame against its scan, with the checks that make them trustworthy.

    values, details, notes, error_mm = frame_geometry(pred_v, pred_f, scan_v, scan_f, settings)

Chamfer, normal consistency and (for watertight meshes) a volumetric IoU whose parity volume is
checked against the signed volume (a self-intersecting or holed mesh is reported "approximate"),
plus a per-vertex distance to the scan for error colors.
"""

from __future__ import annotations

import math
from typing import Any, Protocol

import numpy as np
from scipy.spatial import cKDTree

from igavatar.metrics.geometry import closest_point_on_triangles, evaluate_meshes, sample_surface_uniform, volumetric_iou

#: Scan samples whose faces the error colors are measured against.
ERROR_COLOR_SAMPLES = 100_000


class GeometrySettings(Protocol):
    """How a frame's geometry is measured (`igavatar eval`'s options have these fields)."""

    surface_samples: int
    iou_points: int
    iou_open_meshes: bool
    seed: int


def signed_volume(vertices: np.ndarray, faces: np.ndarray) -> float:
    """Enclosed volume (m^3) by the divergence theorem: the integral of the winding number.

    For a watertight, consistently wound mesh this counts a region covered twice (a
    self-intersection) twice, whereas ray parity counts it zero times: comparing the two exposes
    self-intersections that make a parity inside test wrong.
    """
    tri = np.asarray(vertices, np.float64)[np.asarray(faces)]
    return float(np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])).sum() / 6.0)


def volume_check(vertices: np.ndarray, faces: np.ndarray, n_inside: int, n_points: int, box_volume: float) -> dict:
    """Compare the parity (Monte Carlo) volume with the signed volume of one mesh.

    Args:
        vertices (V, 3), faces (F, 3): the mesh. n_inside, n_points: its parity count among the
        IoU's uniform points. box_volume: volume (m^3) of the box they were drawn in.
    Returns:
        {"signed_volume_m3", "parity_volume_m3", "consistent"}: consistent is False when the two
        differ by more than 4 Monte Carlo standard errors plus 1 %, i.e. when the inside test is
        unreliable (self-intersection, holes or inverted orientation).
    """
    fraction = n_inside / n_points
    parity = fraction * box_volume
    signed = signed_volume(vertices, faces)
    standard_error = box_volume * math.sqrt(max(fraction * (1 - fraction), 1.0 / n_points) / n_points)
    consistent = abs(parity - signed) <= 4 * standard_error + 0.01 * abs(signed)
    return {"signed_volume_m3": signed, "parity_volume_m3": parity, "consistent": bool(consistent)}


def vertex_distance_to_scan(
    vertices: np.ndarray, scan_vertices: np.ndarray, scan_faces: np.ndarray, seed: int, k: int = 4
) -> np.ndarray:
    """Distance (V,) in meters from each vertex to the scan, for the error colors.

    Args:
        vertices: (V, 3) query points. scan_vertices (Vg, 3), scan_faces (Fg, 3): the scan.
        seed: fixes the scan samples. k: nearest samples whose faces are tested exactly.
    Returns:
        (V,) the exact distance to the nearest of the faces holding the k nearest of
        ERROR_COLOR_SAMPLES area-uniform scan samples: an upper bound on the point-to-face distance
        that equals it unless the closest face holds none of those samples. It costs one k-d tree
        query and V * k triangle tests, where the exact search of the metrics would dominate a
        frame's time when run from every predicted vertex.
    """
    samples, sample_face = sample_surface_uniform(scan_vertices, scan_faces, ERROR_COLOR_SAMPLES,
                                                  np.random.default_rng([seed, 3]))
    _, nearest = cKDTree(samples).query(vertices, k=k)
    candidate_faces = scan_faces[sample_face[nearest.reshape(-1)]]  # (V * k, 3)
    tri = scan_vertices[candidate_faces]
    points = np.repeat(vertices, k, axis=0)
    closest = closest_point_on_triangles(points, tri[:, 0], tri[:, 1], tri[:, 2])
    return np.linalg.norm(closest - points, axis=1).reshape(-1, k).min(axis=1)


def frame_geometry(
    pred_vertices: np.ndarray, pred_faces: np.ndarray, gt_vertices: np.ndarray, gt_faces: np.ndarray,
    options: GeometrySettings,
) -> tuple[dict[str, float | None], dict, list[str], np.ndarray]:
    """Every geometry metric of one frame, its diagnostics, notes and per-vertex error (mm).

    Args:
        pred_vertices (Vp, 3), pred_faces (Fp, 3): posed prediction (already its largest component).
        gt_vertices (Vg, 3), gt_faces (Fg, 3): the scan; both world coordinates, meters.
        options: surface samples, IoU points, whether open meshes get a ray-parity IoU, seed.
    Returns:
        (values by metric key, details dict, notes, pred vertex distance to the scan (Vp,) in mm).
    """
    metrics = evaluate_meshes((pred_vertices, pred_faces), (gt_vertices, gt_faces),
                              n_surface=options.surface_samples, n_iou=0, seed=options.seed)
    notes: list[str] = []
    iou_value: float | None = None
    iou_details: dict[str, Any] = {"pred_watertight": metrics.pred_watertight, "gt_watertight": metrics.gt_watertight}
    watertight = metrics.pred_watertight and metrics.gt_watertight
    if options.iou_points <= 0:
        iou_details["status"] = "not computed: --iou-points 0"
    elif not watertight and not options.iou_open_meshes:
        flags = (("prediction", metrics.pred_watertight), ("scan", metrics.gt_watertight))
        which = " and ".join(name for name, ok in flags if not ok)
        iou_details["status"] = (
            f"not computed: the {which} is not watertight (pass --iou-open-meshes for a ray-parity estimate)"
        )
        notes.append(f"IoU {iou_details['status']}")
    else:
        iou = volumetric_iou((pred_vertices, pred_faces), (gt_vertices, gt_faces), options.iou_points, options.seed,
                             require_watertight=False)
        iou_value = float(iou["iou"])
        box_volume = float(np.prod(np.subtract(iou["box_max"], iou["box_min"])))
        checks = {
            "pred": volume_check(pred_vertices, pred_faces, iou["n_inside_pred"], iou["n_points"], box_volume),
            "gt": volume_check(gt_vertices, gt_faces, iou["n_inside_gt"], iou["n_points"], box_volume),
        }
        reliable = watertight and all(c["consistent"] for c in checks.values())
        iou_details.update(
            status="computed" if reliable else "approximate", n_points=iou["n_points"],
            n_intersection=iou["n_intersection"], n_union=iou["n_union"], volume_check=checks,
        )
        if not watertight:
            notes.append("IoU is a ray-parity estimate on a mesh that is not watertight (--iou-open-meshes)")
        for name, check in checks.items():
            if not check["consistent"]:
                notes.append(
                    f"IoU approximate: the {'prediction' if name == 'pred' else 'scan'}'s parity volume "
                    f"{check['parity_volume_m3'] * 1e3:.2f} L differs from its signed volume "
                    f"{check['signed_volume_m3'] * 1e3:.2f} L (self-intersection or holes)"
                )
    distance = vertex_distance_to_scan(pred_vertices, gt_vertices, gt_faces, options.seed)
    pred_center = 0.5 * (pred_vertices.min(0) + pred_vertices.max(0))
    gt_center = 0.5 * (gt_vertices.min(0) + gt_vertices.max(0))
    offset = float(np.linalg.norm(pred_center - gt_center))
    if offset > 0.25:
        notes.append(
            f"the prediction's box center is {offset:.2f} m from the scan's: wrong frame, units (meters expected) or pose?"
        )
    values = {
        "chamfer_l2_cm2": metrics.chamfer_l2_vertices_cm2,
        "normal_consistency_vertices": metrics.normal_consistency_vertices,
        "chamfer_l1_surface_mm": metrics.chamfer_l1_surface_mm,
        "normal_consistency_surface": metrics.normal_consistency_surface,
        "volumetric_iou": iou_value,
    }
    details = {
        "pred_to_gt_cm2": metrics.chamfer_l2_vertices_pred_to_gt_cm2,
        "gt_to_pred_cm2": metrics.chamfer_l2_vertices_gt_to_pred_cm2,
        "surface_pred_to_gt_mm": metrics.surface_pred_to_gt_mm,
        "surface_gt_to_pred_mm": metrics.surface_gt_to_pred_mm,
        "n_dropped_components": metrics.n_dropped_components,
        "pred_vertices": int(len(pred_vertices)), "gt_vertices": int(len(gt_vertices)),
        "box_centre_offset_m": offset,
        "pred_vertex_error_mm": {"median": float(np.median(distance) * 1e3), "p95": float(np.percentile(distance, 95) * 1e3)},
        "volumetric_iou": iou_details,
    }
    return values, details, notes, distance * 1e3
