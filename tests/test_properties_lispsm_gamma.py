"""LiSPSM's warp distance at light angles other than 90 degrees.

Independent truth: Wimmer et al. 2004 (Light Space Perspective Shadow Maps), the optimal near-plane distance of
the warp n_opt = (z_n + sqrt(z_n z_f)) / sin(gamma), z_n and z_f the receivers' view-depth range and gamma the
angle between the view direction and the light direction. At gamma = 90 degrees sin(gamma) = 1, so only other
angles tell a division by sin(gamma) from a multiplication (or from dropping it)."""
from __future__ import annotations

import math

import numpy as np
import pytest
from testkit import ground_samples

from shadowopt.solvers.baselines import baseline
from shadowopt.solvers.cameras import Camera
from shadowopt.solvers.lights import DirectionalLight


def light_at(gamma_deg: float, cam: Camera, azimuth_deg: float = 20.0) -> DirectionalLight:
    """A light direction at `gamma_deg` from the camera's forward axis, turned `azimuth_deg` about it
    (so the light is not in the camera's vertical plane), always travelling downwards."""
    g, a = math.radians(gamma_deg), math.radians(azimuth_deg)
    perp = -math.cos(a) * cam.up + math.sin(a) * cam.right  # unit, perpendicular to forward
    return DirectionalLight.make(math.cos(g) * cam.forward + math.sin(g) * perp)


@pytest.mark.parametrize("gamma", [30.0, 45.0, 60.0, 120.0])
def test_lispsm_n_opt_is_wimmers_formula_at_several_light_angles(gamma):
    cam = Camera.look([0, 2, 0], [0, 0, 1], near=0.1, far=200, resolution=(1280, 720))
    pts, _ = ground_samples(cam)
    light = light_at(gamma, cam)
    sin_g = math.sin(math.radians(gamma))
    assert float(np.degrees(np.arccos(np.dot(cam.forward, light.direction)))) == pytest.approx(gamma)
    depth = (pts - cam.position) @ cam.forward
    zn, zf = float(depth.min()), float(depth.max())
    m = baseline("lispsm", cam, light, pts, None)[0]
    assert m.warp_kind == "perspective", (gamma, m.warp_kind)
    assert m.n_prime == pytest.approx((zn + math.sqrt(zn * zf)) / sin_g, rel=1e-9), gamma


@pytest.mark.parametrize("gamma", [45.0, 120.0])
def test_each_cascade_uses_n_opt_of_its_own_depth_range(gamma):
    """With cascades, z_n and z_f are the cascade's: the receivers' nearest depth to the first split, the
    splits between, the last split to the receivers' farthest depth (the last map's split ends at the camera's
    far plane, its receivers end before)."""
    cam = Camera.look([0, 2, 0], [0, 0, 1], near=0.1, far=200, resolution=(1280, 720))
    pts, _ = ground_samples(cam)
    depth = (pts - cam.position) @ cam.forward
    maps = baseline("lispsm", cam, light_at(gamma, cam), pts, None, cascades=3)
    sin_g = math.sin(math.radians(gamma))
    for i, m in enumerate(maps):
        zn = float(depth.min()) if i == 0 else m.split[0]
        zf = float(depth.max()) if i == len(maps) - 1 else m.split[1]
        assert m.warp_kind == "perspective" and zn < zf
        assert m.n_prime == pytest.approx((zn + math.sqrt(zn * zf)) / sin_g, rel=1e-9), (gamma, i)
