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
