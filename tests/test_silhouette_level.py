"""Where the renderer's silhouette lies against the SDF's zero level (igavatar.model.avatar).

Numerical quadrature of the Laplace density along rays that pass a cylinder (a limb) at a
distance d: the ray whose opacity is 1/2 passes at the closed form `silhouette_offset(beta, r)`.
That offset is the level meshes are made at by default.
"""

from __future__ import annotations

import math

import pytest
import torch

from igavatar.model.fields import SILHOUETTE_RADIUS_M, silhouette_offset
from igavatar.model.fields import LaplaceDensity, LaplaceDensityConfig


def _optical_depth(distance: float, radius: float, density: LaplaceDensity) -> float:
    """Optical depth of a ray perpendicular to a cylinder's axis, passing `distance` outside it."""
    t = torch.linspace(-0.6, 0.6, 400_001, dtype=torch.float64)
    sdf = torch.sqrt(t**2 + (radius + distance) ** 2) - radius
    with torch.no_grad():
        return float(torch.trapezoid(density(sdf), t))


@pytest.mark.parametrize("radius", [0.04, SILHOUETTE_RADIUS_M, 0.15])
@pytest.mark.parametrize("beta", [0.001, 0.003])
def test_the_half_opacity_ray_passes_at_the_silhouette_offset(radius, beta):
    density = LaplaceDensity(LaplaceDensityConfig(beta_init=beta, beta_min=1e-5)).double()
    assert float(density.beta.detach()) == pytest.approx(beta)
    low, high = 0.0, 20 * beta  # optical depth falls with the distance: bisect for ln 2
    for _ in range(40):
        middle = 0.5 * (low + high)
        low, high = (middle, high) if _optical_depth(middle, radius, density) > math.log(2.0) else (low, middle)
    assert silhouette_offset(beta, radius) == pytest.approx(low, rel=0.05)
    assert 1.5 * beta < low < 3.5 * beta  # 2.0 beta at r / beta = 13, 3.1 beta at 150


def test_silhouette_offset_vanishes_for_a_beta_as_large_as_the_limb():
    assert silhouette_offset(0.0) == 0.0
    assert silhouette_offset(1.0) == 0.0  # no tail to speak of: no offset, not a negative one
    assert silhouette_offset(0.001) == pytest.approx(0.001 * math.log(math.sqrt(2 * math.pi * 100) / (2 * math.log(2))))
