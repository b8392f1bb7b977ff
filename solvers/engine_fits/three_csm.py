"""three.js r187's CSM addon (examples/jsm/csm/CSM.js, CSMFrustum.js, CSMShader.js; WebGLRenderer) as pure math:
the cascades it fits for one directional light and one camera pose, from the options its users set
(solvers.engine_fits: the interface; ../shared/reference/engine-settings.md §1.2, checked against the files of
three@0.187.0 as `make setup` installs them under out/web/node_modules/three/examples/jsm/csm/).

Steps, each as the addon does it (file and method in the comment at each step below):
1. breaks b_i (fractions of F = min(camera.far, maxFar)): uniform, logarithmic, or practical with lambda fixed at
   0.5 (CSM.js _getBreaks); b_N = 1.
2. slices: the camera frustum's corners with the far ones scaled to |z| <= maxFar (CSMFrustum.setFromProjectionMatrix),
   cut at view depth b_i F (CSMFrustum.split lerps each corner edge by (b F - n) / (F - n)).
3. one square light camera per slice, side W = max(far-plane diagonal, body diagonal) of the slice
   (CSM.js _updateShadowBounds; fade off: the fade margin is not emulated);
4. per frame (CSM.js update): the slice's corners in the light's orientation R = Matrix4.lookAt(0, lightDirection,
   +Y) (its +z towards the light), their box's centre, z moved to the box's light-most z + lightMargin, x and y
   floored to the texel W / shadowMapSize; the light camera at R c looking along lightDirection (LightShadow
   updateMatrices: lookAt with up +Y, the same axes), orthographic +-W/2, near lightNear, far lightFar.
5. selection (CSMShader.js lights_fragment_begin, fade off): cascade i where view depth / (F - n) lies in
   [b_{i-1}, b_i) with b_{-1} = 0, so the engine switches at view depth b_i (F - n), nearer than the slice's end
   b_i F; past b_N (F - n) = F - n nothing shadows (lit).
6. bias (ShaderChunk/shadowmap_pars_fragment.glsl.js getShadow: shadowCoord.z += shadowBias, shadowed iff it exceeds
   the stored window depth; BasicShadowMap: one nearest texel): the product's receiver constant is -shadowBias in
   window depth (orthographic: (d - lightNear) / (lightFar - lightNear)), the depth texture DEPTH24 (unorm24);
   shadowNormalBias is each cascade light's shadow.normalBias (not a CSM option), world metres along the vertex
   normal (shadowmap_vertex.glsl.js). No caster slope term (CSM sets no polygon offset).
Options read with `||` (cascades, maxFar, mode, shadowMapSize, shadowBias, lightNear, lightFar, lightMargin) take
their default when given 0: emulated (`effective`).

Approximate: the light pass's rasterization is the product's texel-centre ray (renderers.shadow_map_rays), which
agrees with a rasterizer's coverage up to triangle edges inside a texel; casters in front of lightNear are
clipped (no depth clamp in three's light pass), as the depth probe without pancaking does; the map's faces:
both (material.shadowSide = DoubleSide, set by the emitted module); three's default for a front-side material
(back faces only) is not emulated and not offered.
"""
from __future__ import annotations

import math

import numpy as np

from ..cameras import Camera
from ..lights import DirectionalLight
from ..shadow_map import ShadowMap
from .knobs import Knob, validate_settings

ENGINE = "three"
VERSION = "0.187.0"  # npm three (REVISION '187'); Makefile's three.js rule pins it
SHADOW_MAP_TYPE = "BasicShadowMap"  # nearest-texel lookups, the test the emulation scores (the module sets it)
DEPTH_FORMAT = "unorm24"  # WebGLShadowMap.js: DepthTexture(UnsignedIntType) -> DEPTH_COMPONENT24
PRACTICAL_LAMBDA = 0.5  # CSM.js _getBreaks: practicalSplit(..., 0.5, ...), not settable

KNOBS: dict[str, Knob] = {
    "cascades": Knob(3, "int", (1, 8), "number of cascades, one DirectionalLight and map each (CSM.js; `||`: 0 means 3)"),
    "mode": Knob("practical", "choice", ("practical", "uniform", "logarithmic"),
                 "split scheme (CSM.js _getBreaks); practical blends uniform and logarithmic with lambda fixed at "
                 "0.5; 'custom' (a callback) is not offered"),
    "maxFar": Knob(100000.0, "float", (0.01, 1e7), "the shadowed view depth is min(camera.far, maxFar) "
                   "(CSM.js; `||`: 0 means 100000)"),
    "shadowMapSize": Knob(2048, "int", (16, 16384), "each cascade's map side in texels (CSM.js; `||`: 0 means 2048)"),
    "shadowBias": Knob(0.000001, "float", (-0.05, 0.05), "LightShadow.bias of every cascade, added to the receiver's "
                       "window depth: negative removes acne (CSM.js; `||`: 0 means 0.000001)"),
    "shadowNormalBias": Knob(0.0, "float", (0.0, 100.0), "LightShadow.normalBias of every cascade light (not a CSM "
                             "option: the emitted module sets csm.lights[i].shadow.normalBias), metres along the "
                             "receiver's normal"),
    "lightNear": Knob(1.0, "float", (0.001, 1e6), "each cascade's light camera near plane (CSM.js; `||`: 0 means 1)"),
    "lightFar": Knob(2000.0, "float", (0.01, 1e7), "each cascade's light camera far plane (CSM.js; `||`: 0 means 2000)"),
    "lightMargin": Knob(200.0, "float", (0.0, 1e6), "the light camera sits this far beyond the slice's light-most "
                        "corner (CSM.js update; `||`: 0 means 200)"),
    "fade": Knob(False, "bool", (False,), "blending between cascades (CSM.js fade); true is not emulated"),
    "shadowSide": Knob("DoubleSide", "choice", ("DoubleSide",), "faces drawn into the maps (material.shadowSide); "
                       "three's default for front-side materials (back faces only) is not emulated"),
}

# the options CSM.js reads as `data.x || default` (a 0 takes the default)
OR_DEFAULTED = ("cascades", "maxFar", "mode", "shadowMapSize", "shadowBias", "lightNear", "lightFar", "lightMargin")


def validate(settings: dict | None) -> dict:
    """Settings checked and completed with KNOBS' defaults (ValueError naming the field otherwise)."""
    out = validate_settings(ENGINE, KNOBS, settings)
    if out["lightFar"] <= out["lightNear"]:
        raise ValueError(f"settings.lightFar: must exceed lightNear ({out['lightNear']:g}), got {out['lightFar']:g}")
    return out


def effective(settings: dict) -> dict:
    """What CSM.js holds after its constructor: `data.x || default` (a 0 becomes the default)."""
    out = dict(settings)
    for name in OR_DEFAULTED:
        if not out[name]:
            out[name] = KNOBS[name].default
    return out


def faces(settings: dict) -> str:
    """The faces drawn into the maps: both (DoubleSide)."""
    return "both"


def breaks(cascades: int, near: float, far: float, mode: str) -> np.ndarray:
    """CSM.js _getBreaks: b_1 .. b_N as fractions of `far` (= min(camera.far, maxFar)), b_N = 1."""
    i = np.arange(1, cascades, dtype=np.float64)
    uniform = (near + (far - near) * i / cascades) / far  # uniformSplit
    log = near * (far / near) ** (i / cascades) / far  # logarithmicSplit
    if mode == "uniform":
        b = uniform
    elif mode == "logarithmic":
        b = log
    elif mode == "practical":  # practicalSplit: MathUtils.lerp(uniform, log, 0.5)
        b = uniform + (log - uniform) * PRACTICAL_LAMBDA
    else:
        raise ValueError(f"settings.mode: expected one of {', '.join(KNOBS['mode'].domain)}, got {mode!r}")
    return np.concatenate([b, [1.0]])


def frustum_corners(camera: Camera, max_far: float) -> tuple[np.ndarray, np.ndarray]:
    """CSMFrustum.setFromProjectionMatrix(camera.projectionMatrix, maxFar): near and far corners in camera view
    space (4 x 3 each, order (+x,+y), (+x,-y), (-x,-y), (-x,+y)), the far ones scaled so |z| <= maxFar."""
    th = camera.tan_half_fov_y
    tw = th * camera.aspect
    sx = np.array([1.0, 1.0, -1.0, -1.0])
    sy = np.array([1.0, -1.0, -1.0, 1.0])

    def plane(d):
        return np.stack([sx * tw * d, sy * th * d, np.full(4, -d)], axis=1)

    far = plane(camera.far) * min(max_far / camera.far, 1.0)  # perspective: the whole vector scaled
    return plane(camera.near), far


def slices(camera: Camera, settings: dict) -> list[tuple[np.ndarray, np.ndarray]]:
    """CSMFrustum.split: per cascade its (near, far) corners in camera view space."""
    s = effective(validate(settings))
    near_c, far_c = frustum_corners(camera, s["maxFar"])
    n, F = -near_c[0, 2], -far_c[0, 2]
    b = breaks(s["cascades"], camera.near, min(camera.far, s["maxFar"]), s["mode"])
    out = []
    for i in range(len(b)):
        if i == 0:
            lo = near_c
        else:
            a = (b[i - 1] * F - n) / (F - n)
            lo = near_c + (far_c - near_c) * a
        if i == len(b) - 1:
            hi = far_c
        else:
            a = (b[i] * F - n) / (F - n)
            hi = near_c + (far_c - near_c) * a
        out.append((lo, hi))
    return out


def slice_width(near_c: np.ndarray, far_c: np.ndarray) -> float:
    """CSM.js _updateShadowBounds (fade off): max(|far0 - far2|, |far0 - near2|)."""
    return float(max(np.linalg.norm(far_c[0] - far_c[2]), np.linalg.norm(far_c[0] - near_c[2])))


def look_at_rotation(direction: np.ndarray) -> np.ndarray:
    """Matrix4.lookAt(origin, lightDirection, up = +Y) (math/Matrix4.js): columns x, y, z with z = -direction,
    including three's nudge when z is parallel to up."""
    up = np.array([0.0, 1.0, 0.0])
    z = -np.asarray(direction, float)
    z = z / np.linalg.norm(z) if np.linalg.norm(z) > 0 else np.array([0.0, 0.0, 1.0])
    x = np.cross(up, z)
    if np.dot(x, x) == 0:
        z = z.copy()
        if abs(up[2]) == 1:
            z[0] += 0.0001
        else:
            z[2] += 0.0001
        z /= np.linalg.norm(z)
        x = np.cross(up, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return np.stack([x, y, z], axis=1)


def orthographic(half: float, near: float, far: float) -> np.ndarray:
    """OrthographicCamera(-half, half, half, -half, near, far).projectionMatrix (Matrix4.makeOrthographic, WebGL)."""
    p = np.eye(4)
    p[0, 0] = p[1, 1] = 1.0 / half
    p[2, 2] = -2.0 / (far - near)
    p[2, 3] = -(far + near) / (far - near)
    return p


def pancakes(settings: dict) -> bool:
    """Whether casters in front of a light camera's near plane are pancaked onto it: no (three has no depth clamp)."""
    return False


def fit(camera: Camera, light: DirectionalLight, settings: dict, casters_box: tuple | None = None) -> list[ShadowMap]:
    """The CSM addon's cascades for this camera pose and light (module doc), with validated settings; casters_box
    is not used (CSM fits the camera's slices only)."""
    s = effective(validate(settings))
    size = int(s["shadowMapSize"])
    R = look_at_rotation(light.direction)
    cam_to_world = np.linalg.inv(camera.view_matrix())  # camera.matrixWorld
    F = min(camera.far, s["maxFar"])
    b = breaks(s["cascades"], camera.near, F, s["mode"])
    span = F - camera.near  # CSMShader.js: linearDepth = vViewPosition.z / (shadowFar - cameraNear)
    proj_near, proj_far = float(s["lightNear"]), float(s["lightFar"])
    depth = {"mode": "hardware", "format": DEPTH_FORMAT, "chosen_by": "engine",
             "hardware": {"constant": -float(s["shadowBias"]), "slope": 0.0,
                          "normal_offset": float(s["shadowNormalBias"]), "slope_scaled": 0.0, "slope_clamp": 1.0}}
    maps = []
    for i, (lo, hi) in enumerate(slices(camera, settings)):
        W = slice_width(lo, hi)  # _updateShadowBounds: set once, not per frame
        texel = W / size
        corners = np.vstack([lo, hi])
        world = corners @ cam_to_world[:3, :3].T + cam_to_world[:3, 3]
        ls = world @ R  # R^-1 = R^T: world -> the light's orientation
        bmin, bmax = ls.min(axis=0), ls.max(axis=0)
        c = 0.5 * (bmin + bmax)  # Box3.getCenter
        c[2] = bmax[2] + s["lightMargin"]  # update(): _center.z = _bbox.max.z + lightMargin
        c[0] = math.floor(c[0] / texel) * texel  # floor, not round
        c[1] = math.floor(c[1] / texel) * texel
        view = np.eye(4)  # the light camera at R c with R's axes: matrixWorldInverse = [R^T | -c]
        view[:3, :3] = R.T
        view[:3, 3] = -c
        split = (float(b[i - 1] * span) if i > 0 else 0.0, float(b[i] * span))
        smap = ShadowMap(view, orthographic(0.5 * W, proj_near, proj_far), (size, size), split,
                         (proj_near, proj_far), snapped=True)
        smap.depth = {k: (dict(v) if isinstance(v, dict) else v) for k, v in depth.items()}
        maps.append(smap)
    return maps


def fitted_slices(camera: Camera, settings: dict) -> list[tuple[float, float]]:
    """Each cascade's fitted slice in view depth (b_{i-1} F, b_i F): what the light camera covers, beside the
    `split` the shader selects it over."""
    s = effective(validate(settings))
    F = min(camera.far, s["maxFar"])
    b = breaks(s["cascades"], camera.near, F, s["mode"])
    edges = np.concatenate([[camera.near / F], b[:-1]]) * F
    return [(float(lo), float(hi)) for lo, hi in zip(edges, b * F)]


def light_depth_reach(camera: Camera, light: DirectionalLight, settings: dict) -> float:
    """The light camera distance the deepest slice corner lies at, lightMargin + the slice's depth along the light
    (CSM.js update: the camera sits lightMargin beyond the slice box's light-most z): a lightFar below it loses the
    slice's far receivers (their window depth exceeds 1: lit)."""
    s = effective(validate(settings))
    R = look_at_rotation(light.direction)
    cam_to_world = np.linalg.inv(camera.view_matrix())
    reach = 0.0
    for lo, hi in slices(camera, settings):
        z = (np.vstack([lo, hi]) @ cam_to_world[:3, :3].T + cam_to_world[:3, 3]) @ R[:, 2]
        reach = max(reach, float(z.max() - z.min()) + s["lightMargin"])
    return reach
