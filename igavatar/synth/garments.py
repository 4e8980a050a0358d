"""A clothed subject as one watertight surface: the Anny rest mesh pushed outwards per garment region.

    subject = build_clothed_subject(x_rest, faces, weights, skeleton.joint_names, skeleton.rest_joints, "shirt-trousers")
    subject.vertices_canonical, subject.faces, subject.weights   # skin `weights` with the body's bones

Garment regions come from the skinning weights of named Anny bones plus a few lengths measured
along the bones (sleeve, trouser leg, neckline, hairline); every field is diffused over the mesh so
that hems are smooth curves. The offset field is limited by the clearance in front of each vertex
(ray cast along the smoothed normal) and relaxed, and faces that still cross are fixed by shrinking
the offset around them, so the result is a closed surface without self-intersections. Vertices keep
their body weights: the cloth moves with the body under linear blend skinning. Shapes: V vertices,
F faces, J bones, C coverage channels (top, bottom, hair, shoes).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal, get_args

import numpy as np
import pymeshlab
import scipy.sparse as sp
from scipy.spatial import cKDTree

from igavatar.errors import BodyModelError, InputError
from igavatar.geometry.mesh_ops import largest_component, vertex_normals
from igavatar.geometry.raycast import MeshRayCaster

Garment = Literal["shirt-trousers", "dress", "tight"]
GARMENTS: tuple[str, ...] = get_args(Garment)

#: Coverage channels of ClothedSubject.coverage, in order; where several cover a point, the one
#: that comes first in REGION_PRIORITY is outermost (a shirt hangs over the trousers' waistband).
COVERAGE_CHANNELS: tuple[str, ...] = ("top", "bottom", "hair", "shoes")
#: Region ids used by the texture: 0 skin, then 1 + index into COVERAGE_CHANNELS.
REGIONS: tuple[str, ...] = ("skin",) + COVERAGE_CHANNELS
REGION_PRIORITY: tuple[str, ...] = ("hair", "top", "bottom", "shoes")

#: Reference standing height (meters) that the garment lengths below are written for; offsets are
#: scaled by the subject's height over this, so a child's shirt is not 3 cm thick.
REFERENCE_HEIGHT_M = 1.65


@dataclass(frozen=True)
class GarmentSpec:
    """Thicknesses (meters, for a REFERENCE_HEIGHT_M tall subject) and extents of one outfit.

    Attributes:
        top_offset: distance of the shirt/dress top from the torso.
        sleeve_offset: distance of the sleeves from the upper arm.
        sleeve_length: sleeve end as a fraction of the shoulder-to-elbow length (0 = sleeveless).
        hem_below_hip: how far below the hip joints the top ends (negative = above them).
        bottom_offset_hip: trouser distance from the body at the hips.
        bottom_offset_ankle: trouser distance at the trouser hem (wider at the bottom).
        bottom_length: trouser hem as a fraction of the hip-to-ankle length (0 = no trousers).
        waist_above_hip: trouser waistband height above the hip joints.
        hair_offset_top: hair thickness on the crown.
        hair_offset_back: hair thickness at the back of the head (a volume).
        shoe_offset: shoe thickness around the foot (toes are first smoothed into one shape).
        skirt_length: dress skirt hem as a fraction of the hip-to-knee length (0 = no skirt).
        skirt_flare: extra radius of the skirt at its hem relative to the hips.
    """

    top_offset: float
    sleeve_offset: float
    sleeve_length: float
    hem_below_hip: float
    bottom_offset_hip: float
    bottom_offset_ankle: float
    bottom_length: float
    waist_above_hip: float
    hair_offset_top: float
    hair_offset_back: float
    shoe_offset: float
    skirt_length: float = 0.0
    skirt_flare: float = 0.0


GARMENT_SPECS: dict[str, GarmentSpec] = {
    "shirt-trousers": GarmentSpec(
        top_offset=0.03, sleeve_offset=0.025, sleeve_length=0.7, hem_below_hip=0.06,
        bottom_offset_hip=0.015, bottom_offset_ankle=0.03, bottom_length=0.93, waist_above_hip=0.09,
        hair_offset_top=0.025, hair_offset_back=0.045, shoe_offset=0.01,
    ),
    "tight": GarmentSpec(
        top_offset=0.008, sleeve_offset=0.006, sleeve_length=0.35, hem_below_hip=-0.02,
        bottom_offset_hip=0.005, bottom_offset_ankle=0.007, bottom_length=0.93, waist_above_hip=0.04,
        hair_offset_top=0.012, hair_offset_back=0.02, shoe_offset=0.006,
    ),
    "dress": GarmentSpec(
        top_offset=0.02, sleeve_offset=0.015, sleeve_length=0.25, hem_below_hip=0.12,
        bottom_offset_hip=0.0, bottom_offset_ankle=0.0, bottom_length=0.0, waist_above_hip=0.0,
        hair_offset_top=0.03, hair_offset_back=0.06, shoe_offset=0.01,
        skirt_length=0.6, skirt_flare=0.07,
    ),
}


@dataclass(frozen=True)
class ClothedSubject:
    """The clothed rest-pose surface and what it needs to be posed and textured.

    Attributes:
        vertices_canonical: (V, 3) float64 rest-pose (canonical) positions in meters.
        faces: (F, 3) int64, outward-facing, one closed 2-manifold surface.
        weights: (V, J) float32 skinning weights (rows sum to 1), the body's bones.
        coverage: (V, C) float32 in [0, 1], per COVERAGE_CHANNELS, for texturing.
        offsets: (V,) float32 outward displacement from the body surface in meters.
        garment: the outfit name.
    """

    vertices_canonical: np.ndarray
    faces: np.ndarray
    weights: np.ndarray
    coverage: np.ndarray
    offsets: np.ndarray
    garment: str


# --------------------------------------------------------------------------------------------
# Mesh helpers (numpy / scipy; all operate on a vertex array and an (F, 3) face array)


def _adjacency(faces: np.ndarray, num_vertices: int) -> sp.csr_matrix:
    """(V, V) symmetric 0/1 vertex adjacency from the face edges."""
    i = np.concatenate([faces[:, 0], faces[:, 1], faces[:, 2]])
    j = np.concatenate([faces[:, 1], faces[:, 2], faces[:, 0]])
    a = sp.coo_matrix((np.ones(i.size), (i, j)), shape=(num_vertices, num_vertices)).tocsr()
    a = ((a + a.T) > 0).astype(np.float64)
    return a.tocsr()


def _averaging_operator(faces: np.ndarray, num_vertices: int) -> sp.csr_matrix:
    """(V, V) row-stochastic matrix: the mean over each vertex's one-ring neighbours."""
    a = _adjacency(faces, num_vertices)
    degree = np.asarray(a.sum(axis=1)).reshape(-1)
    return (sp.diags(1.0 / np.maximum(degree, 1.0)) @ a).tocsr()


def diffuse(values: np.ndarray, average: sp.csr_matrix, iterations: int, rate: float = 0.5) -> np.ndarray:
    """Explicit umbrella-Laplacian smoothing of per-vertex values: x <- (1 - rate) x + rate * mean(neighbours)."""
    out = np.asarray(values, dtype=np.float64)
    for _ in range(iterations):
        out = (1.0 - rate) * out + rate * (average @ out)
    return out


def self_intersecting_faces(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(F,) bool: faces that intersect a non-adjacent face (MeshLab's exact triangle-triangle test)."""
    mesh_set = pymeshlab.MeshSet()
    mesh_set.add_mesh(pymeshlab.Mesh(vertex_matrix=np.asarray(vertices, np.float64), face_matrix=np.asarray(faces, np.int32)))
    mesh_set.compute_selection_by_self_intersections_per_face()
    return np.asarray(mesh_set.current_mesh().face_selection_array(), dtype=bool)


def is_closed_manifold(faces: np.ndarray) -> bool:
    """Every undirected edge is shared by exactly two faces with opposite orientation (watertight, oriented)."""
    directed = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    undirected = np.sort(directed, axis=1)
    _, counts = np.unique(undirected, axis=0, return_counts=True)
    if not np.all(counts == 2):
        return False
    # Consistent orientation: each directed edge appears once (its twin runs the other way).
    return np.unique(directed, axis=0).shape[0] == directed.shape[0]


def loop_subdivision(faces: np.ndarray, num_vertices: int) -> tuple[sp.csr_matrix, np.ndarray]:
    """One step of Loop subdivision of a closed triangle mesh, as a linear operator.

    Any per-vertex quantity (positions, skinning weights, coverages) is subdivided by
    `new_values = operator @ values`, so they stay consistent with each other.

    Returns:
        operator: (V + E, V) sparse matrix (old vertices first, then one vertex per edge);
        new_faces: (4F, 3) faces over the V + E new vertices, same orientation.
    """
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])  # (3F, 2), face-major blocks
    opposite = np.concatenate([faces[:, 2], faces[:, 0], faces[:, 1]])  # vertex opposite each edge
    sorted_edges = np.sort(edges, axis=1)
    unique_edges, edge_of = np.unique(sorted_edges, axis=0, return_inverse=True)
    edge_of = edge_of.reshape(-1)
    num_edges = unique_edges.shape[0]
    # Edge points: 3/8 of each end + 1/8 of each opposite vertex (closed mesh: two faces per edge).
    rows = [np.repeat(np.arange(num_edges), 2), edge_of]
    cols = [unique_edges.reshape(-1), opposite]
    vals = [np.full(2 * num_edges, 3.0 / 8.0), np.full(opposite.size, 1.0 / 8.0)]
    edge_rows = sp.coo_matrix(
        (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(num_edges, num_vertices)
    ).tocsr()
    # Vertex points: Warren's weights beta = 3 / (8 n) (n > 3), 3/16 (n = 3).
    adjacency = _adjacency(faces, num_vertices)
    n = np.asarray(adjacency.sum(axis=1)).reshape(-1)
    beta = np.where(n > 3, 3.0 / (8.0 * np.maximum(n, 1)), 3.0 / 16.0)
    vertex_rows = (sp.diags(1.0 - n * beta) + sp.diags(beta) @ adjacency).tocsr()
    operator = sp.vstack([vertex_rows, edge_rows]).tocsr()
    e01, e12, e20 = (num_vertices + edge_of[k * faces.shape[0] : (k + 1) * faces.shape[0]] for k in range(3))
    a, b, c = faces[:, 0], faces[:, 1], faces[:, 2]
    new_faces = np.concatenate(
        [np.stack([a, e01, e20], 1), np.stack([b, e12, e01], 1), np.stack([c, e20, e12], 1), np.stack([e01, e12, e20], 1)]
    )
    return operator, new_faces.astype(np.int64)


# --------------------------------------------------------------------------------------------
# Garment regions


def _smoothstep(edge0: float | np.ndarray, edge1: float | np.ndarray, x: np.ndarray) -> np.ndarray:
    """Hermite step from 0 at edge0 to 1 at edge1 (edge0 > edge1 gives a falling step)."""
    t = np.clip((x - edge0) / (edge1 - edge0), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


class _Bones:
    """Looks up Anny bones by name and sums skinning weights over groups of them."""

    def __init__(self, names: Sequence[str], joints: np.ndarray, weights: np.ndarray) -> None:
        self.index = {name: j for j, name in enumerate(names)}
        self.joints = joints
        self.weights = weights
        self.names = list(names)

    def head(self, name: str) -> np.ndarray:
        try:
            return self.joints[self.index[name]]
        except KeyError as exc:
            raise BodyModelError(
                f"garments: bone '{name}' not in the skeleton; garments are defined on Anny's bone names "
                f"(got {len(self.names)} bones, e.g. {self.names[:4]})"
            ) from exc

    def weight_sum(self, prefixes: Sequence[str], side: str | None = None) -> np.ndarray:
        """(V,) summed weight of the bones whose name starts with one of `prefixes` (and ends with .L/.R)."""
        columns = [
            j for name, j in self.index.items()
            if any(name.startswith(p) for p in prefixes) and (side is None or name.endswith(f".{side}"))
        ]
        if not columns:
            raise BodyModelError(f"garments: no bone named {list(prefixes)} (side {side}) in the skeleton")
        return self.weights[:, columns].sum(axis=1)


def _segment_parameter(points: np.ndarray, start: np.ndarray, end: np.ndarray) -> np.ndarray:
    """(V,) position of each point's projection along start->end (0 at start, 1 at end, unclamped)."""
    axis = end - start
    return (points - start) @ axis / float(axis @ axis)


@dataclass(frozen=True)
class _Regions:
    coverage: np.ndarray  # (V, C) soft coverage per COVERAGE_CHANNELS
    target: np.ndarray  # (V, C) desired outward offset of each channel where it covers


def _garment_regions(
    x_rest: np.ndarray, bones: _Bones, spec: GarmentSpec, scale: float, average: sp.csr_matrix
) -> _Regions:
    """Soft coverage and target offsets of each garment channel at every vertex."""
    z = x_rest[:, 2]
    y = x_rest[:, 1]
    head_part = bones.weight_sum(["neck", "head", "eye"])
    foot_part = bones.weight_sum(["foot", "toe"])

    # Position along the arm/leg of each side; a vertex uses the side whose bones weigh it more.
    arm_t, leg_t, arm_part = np.zeros(len(z)), np.zeros(len(z)), np.zeros(len(z))
    arm_weight = {s: bones.weight_sum(["upperarm", "lowerarm", "wrist", "finger", "metacarpal"], s) for s in "LR"}
    leg_weight = {s: bones.weight_sum(["upperleg", "lowerleg", "foot", "toe"], s) for s in "LR"}
    for side in "LR":
        use_arm = arm_weight[side] >= arm_weight["R" if side == "L" else "L"]
        t = _segment_parameter(x_rest, bones.head(f"upperarm01.{side}"), bones.head(f"lowerarm01.{side}"))
        arm_t = np.where(use_arm, t, arm_t)
        arm_part = np.where(use_arm, arm_weight[side], arm_part)
        use_leg = leg_weight[side] >= leg_weight["R" if side == "L" else "L"]
        t = _segment_parameter(x_rest, bones.head(f"upperleg01.{side}"), bones.head(f"foot.{side}"))
        leg_t = np.where(use_leg, t, leg_t)
    hip_z = 0.5 * (bones.head("upperleg01.L")[2] + bones.head("upperleg01.R")[2])
    neck = bones.head("neck01")
    eye = 0.5 * (bones.head("eye.L") + bones.head("eye.R"))
    blur = 0.01 * scale

    # Top: torso above the hem, minus the neck (lower neckline in front), minus the arm past the sleeve.
    hem_z = hip_z - spec.hem_below_hip * scale
    front = _smoothstep(neck[1] + 0.02 * scale, neck[1] - 0.04 * scale, y)  # 1 in front of the neck
    neckline_z = neck[2] - 0.015 * scale - 0.05 * scale * front
    top = _smoothstep(hem_z - blur, hem_z + blur, z)
    top *= 1.0 - head_part * _smoothstep(neckline_z - blur, neckline_z + blur, z)
    top *= 1.0 - arm_part * _smoothstep(spec.sleeve_length - 0.03, spec.sleeve_length + 0.03, arm_t)
    top *= 1.0 - foot_part
    top_target = np.where(arm_part > 0.5, spec.sleeve_offset, spec.top_offset) * scale

    # Bottom: from the waistband down the legs to the trouser hem, never the hands or feet.
    waist_z = hip_z + spec.waist_above_hip * scale
    if spec.bottom_length > 0:
        bottom = _smoothstep(waist_z + blur, waist_z - blur, z)
        bottom *= _smoothstep(spec.bottom_length + 0.015, spec.bottom_length - 0.015, leg_t)
        bottom *= (1.0 - arm_part) * (1.0 - foot_part)
    else:
        bottom = np.zeros_like(z)
    flare = np.clip(leg_t / max(spec.bottom_length, 1e-6), 0.0, 1.0)
    bottom_target = (spec.bottom_offset_hip + (spec.bottom_offset_ankle - spec.bottom_offset_hip) * flare) * scale

    # Hair: the head above the hairline and its back down to the nape; thicker at the back.
    hairline_z = eye[2] + 0.04 * scale
    back = _smoothstep(eye[1] + 0.07 * scale, eye[1] + 0.11 * scale, y)
    hair = head_part * np.maximum(
        _smoothstep(hairline_z - blur, hairline_z + blur, z), back * _smoothstep(neck[2] - blur, neck[2] + blur, z)
    )
    hair_target = (spec.hair_offset_top + (spec.hair_offset_back - spec.hair_offset_top) * back) * scale
    # The hair volume thins out towards the neck so that it does not bulge over the shoulders.
    hair_target *= 0.4 + 0.6 * _smoothstep(neck[2], eye[2], z)

    shoes = foot_part * _smoothstep(0.9, 0.97, leg_t)
    shoe_target = np.full_like(z, spec.shoe_offset * scale)

    coverage = np.stack([top, bottom, hair, shoes], axis=1)
    # Diffusion over ~1-2 cm turns the step functions into smooth hems on the mesh.
    coverage = np.clip(diffuse(coverage, average, iterations=6), 0.0, 1.0)
    target = np.stack([top_target, bottom_target, hair_target, shoe_target], axis=1)
    target = diffuse(target, average, iterations=4)
    return _Regions(coverage=coverage, target=target)


def _outermost_offset(regions: _Regions) -> np.ndarray:
    """(V,) offset of the outermost garment: max over channels of sharpened coverage x target."""
    sharpened = _smoothstep(0.25, 0.75, regions.coverage)
    return (sharpened * regions.target).max(axis=1)


def _one_ring(face_mask: np.ndarray, faces: np.ndarray, average: sp.csr_matrix) -> np.ndarray:
    """(V,) bool: the vertices of the masked faces and their neighbours."""
    touched = np.zeros(average.shape[0], dtype=bool)
    touched[faces[face_mask].reshape(-1)] = True
    return touched | ((average @ touched.astype(np.float64)) > 0)


def _clearance(x_rest: np.ndarray, normals: np.ndarray, caster: MeshRayCaster) -> np.ndarray:
    """(V,) free distance in front of each vertex along its (unit) normal before the body is hit again."""
    start = x_rest + normals * 1e-4
    hits = caster.first_hits(start, normals)
    return np.where(hits.hit, hits.distance, np.inf)


def build_clothed_subject(
    x_rest: np.ndarray,
    faces: np.ndarray,
    weights: np.ndarray,
    bone_names: Sequence[str],
    joints_rest: np.ndarray,
    garment: str = "shirt-trousers",
    *,
    subdivisions: int = 0,
    max_fix_rounds: int = 12,
) -> ClothedSubject:
    """Dress a rest-pose Anny body as one closed surface.

    Args:
        x_rest: (V, 3) rest-pose body vertices in meters (+Z up, face towards -Y).
        faces: (F, 3) triangles; separate shells (eyes, teeth) are dropped.
        weights: (V, J) skinning weights of the body.
        bone_names: the J bone names (Anny's: 'upperarm01.L', 'head', ...).
        joints_rest: (J, 3) rest-pose bone head positions.
        garment: one of GARMENTS.
        subdivisions: Loop subdivision steps applied to the clothed surface (each x4 faces).
        max_fix_rounds: rounds of shrinking the offset (and relaxing the body) around faces that
            still intersect, and of relaxing the seam of the dress skirt.
    Returns:
        a ClothedSubject.
    """
    if garment not in GARMENT_SPECS:
        raise InputError(f"garment '{garment}' is not known; choose one of {', '.join(GARMENTS)}")
    x_rest = np.asarray(x_rest, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    weights = np.asarray(weights, dtype=np.float64)
    joints_rest = np.asarray(joints_rest, dtype=np.float64)
    if x_rest.ndim != 2 or x_rest.shape[1] != 3:
        raise InputError(f"garments: body vertices have shape {x_rest.shape}, expected (V, 3)")
    if weights.shape != (x_rest.shape[0], len(bone_names)):
        raise InputError(
            f"garments: skinning weights have shape {weights.shape}, expected ({x_rest.shape[0]}, {len(bone_names)})"
        )
    if joints_rest.shape != (len(bone_names), 3):
        raise InputError(f"garments: rest joints have shape {joints_rest.shape}, expected ({len(bone_names)}, 3)")
    spec = GARMENT_SPECS[garment]

    kept, faces = largest_component(faces, x_rest.shape[0])
    x_body, weights = x_rest[kept], weights[kept]
    num_vertices = x_body.shape[0]
    average = _averaging_operator(faces, num_vertices)
    scale = float(np.ptp(x_body[:, 2])) / REFERENCE_HEIGHT_M
    bones = _Bones(bone_names, joints_rest, weights)
    regions = _garment_regions(x_body, bones, spec, scale, average)

    # Shoes: toes melt into one smooth shape before the offset (Anny's toes touch each other).
    shoe = regions.coverage[:, COVERAGE_CHANNELS.index("shoes")] * (spec.shoe_offset > 0)
    x_base = x_body.copy()
    if shoe.max() > 0:
        smoothed = diffuse(x_body, average, iterations=40)
        x_base = x_body + shoe[:, None] * (smoothed - x_body)

    normals = vertex_normals(x_base, faces)
    normals = diffuse(normals, average, iterations=10)
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
    # Two facing surfaces each move at most 40% of the gap between them, so they never meet.
    limit = 0.4 * _clearance(x_base, normals, MeshRayCaster(x_base, faces))
    offset = np.minimum(_outermost_offset(regions), limit)
    for _ in range(6):
        offset = np.minimum(diffuse(offset, average, iterations=2), limit)

    x_clothed = x_base + offset[:, None] * normals
    thin = 0.002 * scale
    for _ in range(max_fix_rounds):
        crossing = self_intersecting_faces(x_clothed, faces)
        if not crossing.any():
            break
        touched = _one_ring(crossing, faces, average)
        # Shrink the offset on the crossing faces and their one-ring, then re-smooth ...
        offset = np.where(touched, 0.6 * offset, offset)
        offset = np.minimum(diffuse(offset, average, iterations=1), limit)
        # ... and where there is (almost) no offset left, the body itself crosses (Anny has a few
        # such spots for some phenotypes): relax those vertices towards their neighbours.
        relax = touched & (offset < thin)
        x_base[relax] = 0.5 * x_base[relax] + 0.5 * (average @ x_base)[relax]
        x_clothed = x_base + offset[:, None] * normals

    coverage = regions.coverage
    if spec.skirt_length > 0:
        x_clothed, faces, weights, coverage, offset = _add_skirt(
            x_clothed, faces, weights, coverage, offset, bones, spec, scale
        )
        # The boolean union can leave slivers along the seam that touch: relax them away.
        average = _averaging_operator(faces, x_clothed.shape[0])
        for _ in range(max_fix_rounds):
            crossing = self_intersecting_faces(x_clothed, faces)
            if not crossing.any():
                break
            relax = _one_ring(crossing, faces, average)
            x_clothed[relax] = 0.5 * x_clothed[relax] + 0.5 * (average @ x_clothed)[relax]
    for _ in range(subdivisions):
        operator, faces = loop_subdivision(faces, x_clothed.shape[0])
        x_clothed = operator @ x_clothed
        weights = operator @ weights
        coverage = operator @ coverage
        offset = operator @ offset
    weights = np.clip(weights, 0.0, None)
    weights /= weights.sum(axis=1, keepdims=True)
    return ClothedSubject(
        vertices_canonical=x_clothed,
        faces=faces.astype(np.int64),
        weights=weights.astype(np.float32),
        coverage=np.clip(coverage, 0.0, 1.0).astype(np.float32),
        offsets=offset.astype(np.float32),
        garment=garment,
    )


def _skirt_shell(x_clothed: np.ndarray, bones: _Bones, spec: GarmentSpec, scale: float, segments: int = 96, rings: int = 24):
    """A closed bell-shaped skirt mesh around the hips and thighs; its top sits inside the dress top.

    Each ring is an ellipse around the body's cross-section at that height (arms excluded),
    growing monotonically from just inside the waist to `skirt_flare` beyond the hips at the hem.
    Returns vertices (rings * segments + 2, 3) and outward faces.
    """
    hip_z = 0.5 * (bones.head("upperleg01.L")[2] + bones.head("upperleg01.R")[2])
    knee_z = 0.5 * (bones.head("lowerleg01.L")[2] + bones.head("lowerleg01.R")[2])
    top_z = hip_z + 0.07 * scale
    hem_z = hip_z - spec.skirt_length * (hip_z - knee_z)
    arm = bones.weight_sum(["upperarm", "lowerarm", "wrist", "finger", "metacarpal"]) > 0.1
    body = x_clothed[~arm]
    ring_z = np.linspace(top_z, hem_z, rings)
    band = 0.015 * scale
    centers, half_axes = [], []
    for z in ring_z:
        near = body[np.abs(body[:, 2] - z) < band]
        low, high = near[:, :2].min(axis=0), near[:, :2].max(axis=0)
        centers.append(0.5 * (low + high))
        half_axes.append(0.5 * (high - low))
    centers, half_axes = np.array(centers), np.array(half_axes)
    # Bell profile: from 1 cm inside the waist (hidden in the top) to the flare at the hem, never narrowing.
    s = (top_z - ring_z) / (top_z - hem_z)
    half_axes = np.maximum.accumulate(half_axes, axis=0)
    half_axes = half_axes * (1.0 + 0.06 * s[:, None]) + (-0.01 * scale + (spec.skirt_flare * scale + 0.01 * scale) * s**1.5)[:, None]
    # The skirt hangs straight down: one center for all rings (the hips').
    center = centers[: rings // 3].mean(axis=0)
    angle = np.linspace(0.0, 2.0 * np.pi, segments, endpoint=False)
    ring_xy = center + half_axes[:, None, :] * np.stack([np.cos(angle), np.sin(angle)], axis=1)[None]
    vertices = np.concatenate([ring_xy, np.broadcast_to(ring_z[:, None, None], (rings, segments, 1))], axis=2).reshape(-1, 3)
    top_center, bottom_center = rings * segments, rings * segments + 1
    vertices = np.concatenate([vertices, [[*center, top_z], [*center, hem_z]]])
    faces = []
    k = np.arange(segments)
    k1 = (k + 1) % segments
    for r in range(rings - 1):
        a, b = r * segments + k, r * segments + k1
        c, d = (r + 1) * segments + k, (r + 1) * segments + k1
        # Counter-clockwise seen from outside (angle grows counter-clockwise seen from +Z, z falls with r).
        faces += [np.stack([a, c, b], 1), np.stack([b, c, d], 1)]
    faces.append(np.stack([np.full(segments, top_center), k, k1], 1))
    last = (rings - 1) * segments
    faces.append(np.stack([np.full(segments, bottom_center), last + k1, last + k], 1))
    return vertices, np.concatenate(faces).astype(np.int64)


def _add_skirt(
    x_clothed: np.ndarray,
    faces: np.ndarray,
    weights: np.ndarray,
    coverage: np.ndarray,
    offset: np.ndarray,
    bones: _Bones,
    spec: GarmentSpec,
    scale: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Union the clothed body with a skirt shell (exact mesh boolean) and carry the vertex attributes over.

    Vertices that survive from the clothed body keep their attributes; new ones (skirt, and the curve
    where the skirt meets the body) start from the nearest body vertex and their skinning weights are
    then diffused over the skirt with the body vertices held fixed, so the skirt blends the hips and
    both thighs smoothly instead of tearing between the legs.
    """
    skirt_vertices, skirt_faces = _skirt_shell(x_clothed, bones, spec, scale)
    mesh_set = pymeshlab.MeshSet()
    mesh_set.add_mesh(pymeshlab.Mesh(vertex_matrix=x_clothed, face_matrix=faces.astype(np.int32)))
    mesh_set.add_mesh(pymeshlab.Mesh(vertex_matrix=skirt_vertices, face_matrix=skirt_faces.astype(np.int32)))
    mesh_set.generate_boolean_union(first_mesh=0, second_mesh=1)
    union = mesh_set.current_mesh()
    x_union = np.asarray(union.vertex_matrix(), dtype=np.float64)
    faces_union = np.asarray(union.face_matrix(), dtype=np.int64)
    if not is_closed_manifold(faces_union):
        raise BodyModelError("garments: the dress skirt union is not a closed surface; try another phenotype")

    distance, nearest = cKDTree(x_clothed).query(x_union)
    original = distance < 1e-7
    new_weights = weights[nearest].copy()
    new_coverage = coverage[nearest].copy()
    new_coverage[~original] = 0.0
    new_coverage[~original, COVERAGE_CHANNELS.index("top")] = 1.0
    new_offset = np.where(original, offset[nearest], distance)
    average = _averaging_operator(faces_union, x_union.shape[0])
    free = ~original
    for _ in range(200):
        new_weights[free] = (average @ new_weights)[free]
    return x_union, faces_union, new_weights, new_coverage, new_offset
