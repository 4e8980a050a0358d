"""The masks' visual hull in canonical space and the free-space bound it puts on the SDF.

A tiny analytic scene: two spheres (two "legs" with a gap between them) seen by a turntable of
cameras, posed by an identity skeleton of one bone. The hull must keep both spheres, rule out the
gap, lower-bound the true SDF where it rules points out, and its hinge must carve a web that
joins the spheres in an SDF fitted to the wrong (webbed) shape.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from igavatar.model.deformer import FastSnarfDeformer
from igavatar.model.fields import SDFField, SDFFieldConfig
from igavatar.model.hashgrid import HashGridConfig
from igavatar.render.cameras import turntable_cameras
from igavatar.render.rays import pixel_rays
from igavatar.training.data import TrainingData
from igavatar.training.optim import adam
from igavatar.training.visual_hull import canonical_visual_hull, free_space_loss

CENTERS = torch.tensor([[-0.25, 0.0, 0.0], [0.25, 0.0, 0.0]])
RADIUS = 0.15
BOX = torch.tensor([[-0.6, -0.3, -0.4], [0.6, 0.3, 0.4]])
UP, FRONT = torch.tensor([0.0, 0.0, 1.0]), torch.tensor([0.0, -1.0, 0.0])


def true_sdf(x: torch.Tensor) -> torch.Tensor:
    """Union of the two spheres: (P, 3) -> (P,)."""
    return ((x[:, None, :] - CENTERS[None]).norm(dim=-1) - RADIUS).amin(dim=1)


def webbed_sdf(x: torch.Tensor) -> torch.Tensor:
    """The spheres joined by a slab between them (the web to carve)."""
    slab = torch.stack(((x[:, 0].abs() - 0.25), (x[:, 1].abs() - 0.05), (x[:, 2].abs() - 0.1)), dim=-1).amax(dim=-1)
    return torch.minimum(true_sdf(x), slab)


def camera_rays(K: torch.Tensor, w2c: torch.Tensor, size: int):
    """Per camera: (origin (3,), unit directions (size * size, 3)) through its pixels, row-major, float64."""
    v, u = torch.meshgrid(torch.arange(size, dtype=torch.float64), torch.arange(size, dtype=torch.float64), indexing="ij")
    pixels_xy = torch.stack((u, v), dim=-1).reshape(-1, 2)
    for k, extrinsic in zip(K.double(), w2c.double()):
        origins, directions = pixel_rays(k, extrinsic, pixels_xy)
        yield origins[0], directions


def sphere_masks(K: torch.Tensor, w2c: torch.Tensor, size: int) -> torch.Tensor:
    """(N, size, size) bool silhouettes of the two spheres, by ray-sphere intersection."""
    masks = []
    for origin, directions in camera_rays(K, w2c, size):
        hit = torch.zeros(directions.shape[0], dtype=torch.bool)
        for center in CENTERS.double():
            to_center = center - origin
            along = directions @ to_center
            closest = (to_center.square().sum() - along.square()).clamp_min(0).sqrt()
            hit |= (closest <= RADIUS) & (along > 0)
        masks.append(hit.reshape(size, size))
    return torch.stack(masks)


def scene(n_views: int = 24, size: int = 64) -> tuple[FastSnarfDeformer, TrainingData]:
    K, w2c = turntable_cameras(BOX[0], BOX[1], n_views, size, size, up=UP, front=FRONT, elevation=math.radians(5.0))
    K = K.expand(n_views, 3, 3) if K.ndim == 2 else K
    masks = sphere_masks(K, w2c, size)
    deformer = FastSnarfDeformer(torch.ones(1, 8, 8, 8), BOX[0] - 0.1, BOX[1] + 0.1)
    data = TrainingData(
        frame_names=[f"f{i}" for i in range(n_views)],
        images=torch.zeros(n_views, size, size, 3, dtype=torch.uint8),
        masks=masks, K=K.float(), w2c=w2c.float(),
        bone_transforms=torch.eye(4).expand(n_views, 1, 4, 4).clone(),
        pose_condition=torch.zeros(n_views, 3), posed_boxes=BOX.expand(n_views, 2, 3).clone(),
        train_indices=torch.arange(n_views),
    )
    return deformer, data


def test_hull_keeps_the_shape_rules_out_the_gap_and_lower_bounds_the_sdf():
    deformer, data = scene()
    hull = canonical_visual_hull(deformer, data, BOX, cell_size=0.02, mask_dilation_px=1)
    rng = torch.Generator().manual_seed(0)
    inside = CENTERS.repeat_interleave(200, 0) + (torch.rand(400, 3, generator=rng) - 0.5) * RADIUS
    inside = inside[true_sdf(inside) < -0.02]
    assert (hull.free_distance(inside) == 0).all(), "the hull carves the subject itself"
    gap = torch.tensor([[0.0, 0.0, z] for z in np.linspace(-0.06, 0.06, 7)], dtype=torch.float32)
    assert (hull.free_distance(gap) > 0.02).all(), "the gap between the spheres is not free space"
    # Where the hull rules a point out, its bound never exceeds the true distance (+ a cell).
    x = BOX[0] + torch.rand(20000, 3, generator=rng) * (BOX[1] - BOX[0])
    bound = hull.free_distance(x)
    ruled_out = bound > 0
    assert ruled_out.float().mean() > 0.5
    assert (bound[ruled_out] <= true_sdf(x[ruled_out]) + 0.03).all()


def test_free_space_hinge_carves_a_web_and_leaves_the_shape():
    deformer, data = scene()
    hull = canonical_visual_hull(deformer, data, BOX, cell_size=0.02, mask_dilation_px=1)
    config = SDFFieldConfig(hash_grid=HashGridConfig(n_levels=4, log2_hashmap_size=12, base_resolution=8,
                                                     finest_resolution=64), hidden_dim=16, feature_dim=8)
    torch.manual_seed(0)  # the field's initial weights, independent of what ran before
    field = SDFField(config, BOX[0], BOX[1])
    optimizer = adam(field.parameters(), lr=1e-2)
    rng = torch.Generator().manual_seed(1)
    for _ in range(120):  # fit the webbed shape
        x = BOX[0] + torch.rand(2048, 3, generator=rng) * (BOX[1] - BOX[0])
        loss = (field(x)[0] - webbed_sdf(x)).abs().mean()
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    web = torch.tensor([[0.0, 0.0, 0.0], [0.05, 0.0, 0.03], [-0.05, 0.0, -0.03]])
    with torch.no_grad():
        assert (field(web)[0] < 0).all(), "the webbed fit should fill the gap before carving"
    for _ in range(120):  # the hull's hinge, while the (webbed) fit goes on where the hull has no say
        x = BOX[0] + torch.rand(2048, 3, generator=rng) * (BOX[1] - BOX[0])
        bound = hull.free_distance(x)
        sdf = field(x)[0]
        kept = bound == 0
        loss = 5.0 * free_space_loss(sdf, bound, slack=0.02) + (sdf[kept] - webbed_sdf(x[kept])).abs().mean()
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    with torch.no_grad():
        assert (field(web)[0] > 0).all(), "the web was not carved"
        assert (field(CENTERS)[0] < -0.05).all(), "carving removed the spheres"


def test_free_space_loss_is_a_one_sided_hinge():
    sdf = torch.tensor([-0.1, 0.0, 0.2, -0.3], requires_grad=True)
    bound = torch.tensor([0.1, 0.1, 0.1, 0.0])  # the last point is unconstrained
    loss = free_space_loss(sdf, bound)
    assert math.isclose(float(loss.detach()), (0.2 + 0.1 + 0.0) / 3, rel_tol=1e-6)
    loss.backward()
    assert sdf.grad[2] == 0 and sdf.grad[3] == 0 and sdf.grad[0] < 0
    assert float(free_space_loss(sdf, torch.zeros(4)).detach()) == 0.0
