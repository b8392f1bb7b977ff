"""Filament's own directional shadow fit (google/filament filament/src/ShadowMap.cpp updateDirectional and
ShadowMapManager.cpp updateCascadeShadowMaps, the versions read: ShadowMap.cpp with `USE_DEPTH_CLAMP = false`, the
light view's up +Y and the LiSPSM rotation L only with LiSPSM) as pure math: the maps it fits for one directional
light, one camera pose and the scene's renderable bounds, from the LightManager ShadowOptions its users set
(solvers.engine_fits: the interface; ../shared/reference/engine-settings.md §3 summarizes a newer main).

Unlike three's CSM, Filament fits to the scene: `fit` needs the world AABBs of the renderables (`boxes`, every
one casting and receiving, as a glTF asset loaded with shadows on): fit(camera, light, settings, boxes).

Steps, each as Filament does it (the function at each step below names Filament's):
1. scene info (ShadowMap::SceneInfo, updateSceneInfoDirectional): the casters' and receivers' union boxes; the
   casters' light-space z extent (per box, Aabb::transform); the receivers' view-space depth extent.
2. splits (ShadowMapManager::updateCascadeShadowMaps, CascadeSplits): view depths d_i = near + (far - near) p_i over
   near = max(camera near, receivers' nearest), far = min(camera far or shadowFar, receivers' farthest)
   (debug tightly_bound_scene, on by default, not in stable mode); p = 0, cascadeSplitPositions, 1.
3. per cascade (updateDirectional): the cascade's slice of the camera frustum clipped by the receivers' box
   (intersectFrustumWithBox: slice corners in the box, box corners in the whole camera frustum, edge crossings);
   light view Mv looking along the light (up +Y) with its near plane at the casters' light-most z; far = the
   farthest clipped point, at least the casters' farthest (far_uses_shadowcasters); Mp orthographic in z.
4. LiSPSM (lispsm and not stable, applyLISPSM): L turns light-space y towards the camera's forward; the warp
   W = warpFrustum(nopt, nopt + d) T(-p) with nopt from shadowNearHint / shadowFarHint, when sin(L, V) > 0.02.
5. focus F (not stable): the clipped points' x-y bounds in W L Mp Mv, intersected with the casters' box seen in the
   light frustum (focus_shadowcasters); stable: a sphere (the view frustum's, or the receivers' box when smaller),
   scale quantized, offset snapped to 2-texel multiples (snapLightFrustum).
6. the map: S = F W L Mp Mv onto the inner mapSize - 2 texels (getViewport: a 1-texel border, outside which a
   lookup finds no caster: lit), DEPTH16; selection (shader) by view depth: cascade i over [d_i, d_{i+1}), the
   last one beyond.
7. bias, in the product's units: polygon offset in the light pass (ShadowMapManager: {-polygonOffsetSlope,
   -polygonOffsetConstant} for reversed Z): slope_scaled = polygonOffsetSlope, polygonOffsetConstant / 65535 into
   the constant; constantBias moves the casters along the light (the light camera's model Mv translate(direction
   constantBias)): constantBias dD/dd into the constant; the receiver moved 0.5 normalBias texel sin(theta) along
   its normal (shadowBias, texelSizeAtOneMeterWs of the first cascade).

Approximate: the receiver's normal offset is taken at sin(theta) = 1 (the product's normal offset has no angle
term), so it is too large where the light meets the receiver steeply; under LiSPSM constantBias' stored-depth
shift is taken at the map's centre (it varies along the warp axis); the lookup is one nearest texel, where Filament
filters with PCF (3x3 hardware-compare taps); renderables' boxes are taken as given (Filament uses its own world
AABBs of each renderable); the world origin at the camera (debug camera_at_origin) moves stable mode's snapping
grid, which is not emulated; float32 arithmetic is float64 here.
"""
from __future__ import annotations

import math

import numpy as np

from ..cameras import Camera
from ..lights import DirectionalLight
from ..shadow_map import ShadowMap
from .knobs import Knob, validate_settings

ENGINE = "filament"
VERSION = "1.53.4"  # npm filament (Makefile); its web build cannot take ShadowOptions (docs/engines.md)
SHADOW_MAP_TYPE = "PCF"  # Filament's default View shadow type; the emulation scores one nearest texel
DEPTH_FORMAT = "unorm16"  # ShadowMapManager::calculateTextureRequirements: DEPTH16
UNORM16_STEPS = 65535.0  # the polygon offset's constant unit r on a DEPTH16 map
DEFAULT_SPLITS = (0.125, 0.25, 0.5)  # LightManager.h cascadeSplitPositions (not a knob: the web build cannot set it)
LISPSM_MIN_SIN = 0.02  # applyLISPSM: no warp under ~1 degree between the light and the view
STABLE_QUANTUM = 0.0625  # updateDirectional, stable: the focus scale quantized in world units
BOX_EPSILON = 1.0 / 8192.0  # intersectFrustumWithBox: box corners within this of the frustum's planes are inside

_POWERS = tuple(2 ** k for k in range(3, 14))
KNOBS: dict[str, Knob] = {
    "mapSize": Knob(1024, "choice", _POWERS, "each cascade's map side in texels, a power of two (LightManager.h); "
                    "the usable area is mapSize - 2 (a 1-texel border)"),
    "shadowCascades": Knob(1, "int", (1, 4), "number of cascades (LightManager.h), split at cascadeSplitPositions' "
                           "defaults 0.125, 0.25, 0.5 (not offered: the web build cannot set them)"),
    "constantBias": Knob(0.001, "float", (0.0, 10.0), "metres the casters move away from the light in the light pass "
                         "(ShadowMap.cpp updateDirectional)"),
    "normalBias": Knob(1.0, "float", (0.0, 100.0), "the receiver moves 0.5 normalBias texel sin(theta) along its "
                       "normal (ShadowMapManager.cpp shadowBias)"),
    "shadowFar": Knob(0.0, "float", (0.0, 1e7), "view depth beyond which nothing is shadowed; 0: the camera's far "
                      "plane (LightManager.h)"),
    "shadowNearHint": Knob(1.0, "float", (0.0, 1e7), "LiSPSM's virtual near distance (applyLISPSM dzn)"),
    "shadowFarHint": Knob(100.0, "float", (0.0, 1e7), "LiSPSM's virtual far distance (applyLISPSM dzf)"),
    "stable": Knob(False, "bool", (False, True), "a bounding sphere, quantized scale, snapped offset; no LiSPSM"),
    "lispsm": Knob(True, "bool", (False, True), "the LiSPSM warp (C++ API; the web build's ShadowOptions has no "
                   "such field: on)"),
    "polygonOffsetConstant": Knob(0.5, "float", (0.0, 1e4), "hardware depth offset of the casters in DEPTH16 steps"),
    "polygonOffsetSlope": Knob(2.0, "float", (0.0, 100.0), "hardware slope-scaled depth offset of the casters"),
}


def validate(settings: dict | None) -> dict:
    """Settings checked and completed with KNOBS' defaults (ValueError naming the field otherwise)."""
    return validate_settings(ENGINE, KNOBS, settings)


def effective(settings: dict) -> dict:
    """What Filament holds: the settings as given (no `||` defaults)."""
    return dict(settings)


def faces(settings: dict) -> str:
    """The faces drawn into the maps: both (the light pass culls as the material does; the test's glTF materials
    are double-sided)."""
    return "both"


def scene_boxes(vertices: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """The renderables' world AABBs of a scene drawn as one renderable (one glTF mesh): one box."""
    v = np.asarray(vertices, np.float64).reshape(-1, 3)
    return [(v.min(axis=0), v.max(axis=0))]


def light_view(direction, position=(0.0, 0.0, 0.0)) -> np.ndarray:
    """ShadowMap::getDirectionalLightViewMatrix: world -> light view looking along `direction` (-Z), up +Y (or
    (0, 0, 1) rotated in when the light is within ~2.6 degrees of vertical), from `position`."""
    z = np.asarray(direction, np.float64)
    up = np.array([0.0, 1.0, 0.0])
    if abs(z @ up) > 0.999:
        up = np.array([up[2], up[0], up[1]])
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    y = np.cross(x, z)
    m = np.eye(4)
    m[0, :3], m[1, :3], m[2, :3] = x, y, -z  # the inverse of the rigid model [x y -z | position]
    m[:3, 3] = -m[:3, :3] @ np.asarray(position, np.float64)
    return m


def _project(m: np.ndarray, p: np.ndarray) -> np.ndarray:
    """mat4f::project: (m p).xyz / w for points (n, 3)."""
    h = np.asarray(p, np.float64) @ m[:3, :3].T + m[:3, 3]
    w = np.asarray(p, np.float64) @ m[3, :3] + m[3, 3]
    return h / w[:, None]


def _corners(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """A box's 8 corners, x on bit 0, y on bit 1, z on bit 2 (Aabb::getCorners)."""
    return np.array([[(hi if k & 1 else lo)[0], (hi if k & 2 else lo)[1], (hi if k & 4 else lo)[2]] for k in range(8)])


# hexahedra indexed as _corners: the 12 edges (one bit flipped) and 6 faces (one bit fixed), as sBoxSegments/Quads
_EDGES = [(a, a | (1 << b)) for a in range(8) for b in range(3) if not a & (1 << b)]
_FACES = [tuple(k for k in (0, 1 << ((b + 1) % 3), (1 << ((b + 1) % 3)) | (1 << ((b + 2) % 3)), 1 << ((b + 2) % 3)))
          for b in range(3)]
_QUADS = [tuple(v | side for v in q) for b, q in enumerate(_FACES) for side in (0, 1 << b)]


def _segment_triangle(s0, s1, t0, t1, t2):
    """ShadowMap::intersectSegmentWithTriangle (Akenine-Moller et al., Real-Time Rendering): the crossing or None."""
    e1, e2, d = t1 - t0, t2 - t0, s1 - s0
    q = np.cross(d, e2)
    a = e1 @ q
    if abs(a) < 1.0 / 65536.0:
        return None
    s = s0 - t0
    u = (s @ q) * np.sign(a)
    r = np.cross(s, e1)
    v = (d @ r) * np.sign(a)
    if u < 0 or v < 0 or u + v > abs(a):
        return None
    t = (e2 @ r) * np.sign(a)
    if t < 0 or t > abs(a):
        return None
    return s0 + d * (t / abs(a))


def _crossings(segments: np.ndarray, quads: np.ndarray) -> list[np.ndarray]:
    """ShadowMap::intersectFrustum: each edge of `segments` against the faces of `quads`, at most 2 per edge."""
    out = []
    for i0, i1 in _EDGES:
        hits = 0
        for q in _QUADS:
            if hits == 2:
                break
            t0, t1, t2, t3 = (quads[k] for k in q)
            p = _segment_triangle(segments[i0], segments[i1], t0, t1, t2)
            if p is None:
                p = _segment_triangle(segments[i0], segments[i1], t0, t2, t3)
            if p is not None:
                out.append(p)
                hits += 1
    return out


def _planes(clip_from_world: np.ndarray) -> np.ndarray:
    """Frustum(m): the 6 planes (n, d), normals outward, normalized (inside: n.p + d <= 0)."""
    m = clip_from_world
    rows = [-(m[3] + m[0]), -(m[3] + m[1]), -(m[3] - m[0]), -(m[3] - m[1]), -(m[3] - m[2]), -(m[3] + m[2])]
    pl = np.array(rows)
    return pl / np.linalg.norm(pl[:, :3], axis=1, keepdims=True)


def clip_box(planes: np.ndarray, frustum_corners: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """ShadowMap::intersectFrustumWithBox: points on the hull of (frustum x box): the frustum's corners in the box,
    the box's corners inside `planes` (with BOX_EPSILON), and the edge crossings both ways."""
    inside = np.all((frustum_corners >= lo) & (frustum_corners <= hi), axis=1)
    pts = list(frustum_corners[inside])
    if len(pts) == 8:
        return np.array(pts)
    box = _corners(lo, hi)
    box_in = np.all(box @ planes[:, :3].T + planes[:, 3] <= BOX_EPSILON, axis=1)
    pts += list(box[box_in])
    if box_in.sum() < 8:
        pts += _crossings(box, frustum_corners) + _crossings(frustum_corners, box)
    return np.array(pts).reshape(-1, 3)


def _perspective(camera: Camera, far: float) -> np.ndarray:
    """The camera's culling projection (OpenGL perspective with its near and `far`)."""
    th = camera.tan_half_fov_y
    n, f = camera.near, far
    p = np.zeros((4, 4))
    p[0, 0], p[1, 1] = 1.0 / (th * camera.aspect), 1.0 / th
    p[2, 2], p[2, 3], p[3, 2] = -(f + n) / (f - n), -2.0 * f * n / (f - n), -1.0
    return p


def _slice(camera: Camera, d0: float, d1: float) -> np.ndarray:
    """computeFrustumCorners at view depths d0 (near, bit 2 set) and d1 (far), in world space, _corners' order."""
    th = camera.tan_half_fov_y
    tw = th * camera.aspect
    to_world = np.linalg.inv(camera.view_matrix())
    pts = []
    for k in range(8):
        d = d0 if k & 4 else d1
        pts.append([(1 if k & 1 else -1) * tw * d, (1 if k & 2 else -1) * th * d, -d])
    pts = np.array(pts)
    return pts @ to_world[:3, :3].T + to_world[:3, 3]


def _box_z(view: np.ndarray, boxes) -> tuple[float, float]:
    """Aabb::transform of each box by a rigid `view`: (greatest z, least z) over them."""
    z = [(_corners(lo, hi) @ view[2, :3] + view[2, 3]) for lo, hi in boxes]
    return float(max(v.max() for v in z)), float(min(v.min() for v in z))


def splits(camera: Camera, settings: dict, boxes) -> np.ndarray:
    """ShadowMapManager::updateCascadeShadowMaps / CascadeSplits: the view depths d_0 .. d_N of the cascades."""
    s = validate(settings)
    far = s["shadowFar"] if s["shadowFar"] > 0 else camera.far
    near_d, far_d = camera.near, far
    if not s["stable"]:  # tightly_bound_scene: the receivers' view-depth extent
        zmax, zmin = _box_z(camera.view_matrix(), boxes)
        near_d, far_d = max(near_d, -zmax), min(far_d, -zmin)
    n = s["shadowCascades"]
    p = np.array([0.0, *DEFAULT_SPLITS[: n - 1], 1.0])
    return near_d + (far_d - near_d) * p


def _lispsm(camera: Camera, s: dict, LMpMv: np.ndarray, hull: np.ndarray, direction, far: float):
    """ShadowMap::applyLISPSM: (W, Wp), both identity when the warp is not applied."""
    fwd = np.asarray(camera.forward, np.float64)
    lov = float(fwd @ direction)
    sin_lv = math.sqrt(max(0.0, 1.0 - lov * lov))
    dzn = max(0.0, s["shadowNearHint"] - camera.near)
    dzf = max(0.0, far - s["shadowFarHint"])
    vz = hull @ camera.view_matrix()[2, :3] + camera.view_matrix()[2, 3]
    zn, zf = max(camera.near, float(-vz.max())), min(far, float(-vz.min()))
    y = _project(LMpMv, hull)[:, 1]
    n, f = float(y.min()), float(y.max())
    d = abs(f - n)
    z0, z1 = zn, zn + d * sin_lv
    if not (sin_lv > LISPSM_MIN_SIN and 3.0 * (dzn / (zf - zn)) < 2.0):
        return np.eye(4), np.eye(4)
    vz0 = max(0.0, zn, camera.near + dzn, z0)
    vz1 = max(0.0, min(zf, far - dzf, z1))
    nopt = max((z0 + math.sqrt(vz0 * vz1)) / sin_lv, dzn / (2.0 - 3.0 * (dzn / (zf - zn))))
    cam_ls = _project(LMpMv, np.asarray(camera.position, np.float64)[None])[0]
    Wv = np.eye(4)
    Wv[:3, 3] = -np.array([cam_ls[0], n - nopt, 0.0])
    Wp = warp_frustum(nopt, nopt + d)
    return Wp @ Wv, Wp


def warp_frustum(n: float, f: float) -> np.ndarray:
    """ShadowMap::warpFrustum: a frustum looking along +y with x, z in [-1, 1] at the near plane."""
    A, B = (f + n) / (f - n), -2.0 * n * f / (f - n)
    return np.array([[n, 0, 0, 0], [0, A, 0, B], [0, 0, n, 0], [0, 1.0, 0, 0]])


def _bounds2d(m: np.ndarray, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    q = _project(m, pts)[:, :2]
    return q.min(axis=0), q.max(axis=0)


def _focus(s2: np.ndarray, o2: np.ndarray) -> np.ndarray:
    F = np.eye(4)
    F[0, 0], F[1, 1], F[0, 3], F[1, 3] = s2[0], s2[1], o2[0], o2[1]
    return F


def _texture_mapping(size: int) -> np.ndarray:
    """ShadowMap::getTextureCoordsMapping (OpenGL, one map as the atlas): NDC -> the inner viewport's (u, v, 1 - D)."""
    Mt = np.array([[0.5, 0, 0, 0.5], [0, 0.5, 0, 0.5], [0, 0, -0.5, 0.5], [0, 0, 0, 1.0]])
    vp = np.eye(4)
    vp[0, 0] = vp[1, 1] = (size - 2) / size
    vp[0, 3] = vp[1, 3] = 1.0 / size
    return vp @ Mt


def texel_size(St: np.ndarray, MtF: np.ndarray, Wp: np.ndarray, warped: bool, size: int) -> float:
    """ShadowMap::texelSizeWorldSpace: one texel's world size, at the map's centre under LiSPSM (its JACOBIAN_ESTIMATE
    reference path), from the 3x3 part of St otherwise."""
    res = 1.0 / (size - 2)
    if not warped:
        inv = np.linalg.inv(St[:3, :3])
        return float(max(np.linalg.norm(inv[:, 0]), np.linalg.norm(inv[:, 1])) * res)
    Si = np.linalg.inv(MtF @ Wp)
    p = np.array([[0.5, 0.5, 0.0], [0.5 + res, 0.5, 0.0], [0.5, 0.5 + res, 0.0]])
    q = _project(Si, p)
    return float(max(np.linalg.norm(q[1] - q[0]), np.linalg.norm(q[2] - q[0])))


def fit(camera: Camera, light: DirectionalLight, settings: dict, boxes=None) -> list[ShadowMap]:
    """Filament's maps for this camera pose, light and scene (`boxes`: the renderables' world AABBs, e.g.
    scene_boxes(vertices)); [] when Filament draws no shadow (module doc)."""
    if not boxes:
        raise ValueError("boxes: Filament fits its maps to the scene: give the renderables' world AABBs "
                         "(accepted: a list of (min, max), e.g. engine_fits.filament.scene_boxes(vertices))")
    s = validate(settings)
    far = s["shadowFar"] if s["shadowFar"] > 0 else camera.far
    # ShadowMapManager: the shader's normal bias comes from a first fit over the whole camera frustum (the culling
    # pass, csNearFar = [-1, 1]), whatever the cascades
    whole = _fit_slice(camera, light, s, boxes, camera.near, far)
    if whole is None:
        return []
    normal_offset = 0.5 * s["normalBias"] * whole[1]
    d = splits(camera, settings, boxes)
    maps = []
    for i in range(len(d) - 1):
        one = _fit_slice(camera, light, s, boxes, float(d[i]), float(d[i + 1]))
        if one is None:
            continue
        smap = one[0]
        smap.split = (float(d[i]) if i else 0.0, float(d[i + 1]) if i < len(d) - 2 else float("inf"))
        smap.depth["hardware"]["normal_offset"] = normal_offset
        maps.append(smap)
    return maps


def _fit_slice(camera: Camera, light: DirectionalLight, s: dict, boxes, d0: float, d1: float):
    """ShadowMap::updateDirectional for the camera slice [d0, d1]: (ShadowMap, texel world size), None when Filament
    finds no visible shadow."""
    size = int(s["mapSize"])
    direction = np.asarray(light.direction, np.float64)
    far = s["shadowFar"] if s["shadowFar"] > 0 else camera.far
    rlo = np.min([b[0] for b in boxes], axis=0)
    rhi = np.max([b[1] for b in boxes], axis=0)
    Mv0 = light_view(direction)
    cast_near, cast_far = _box_z(Mv0, boxes)  # updateSceneInfoDirectional: lsNearFar
    planes = _planes(_perspective(camera, far) @ camera.view_matrix())  # the whole camera frustum's planes
    use_lispsm = s["lispsm"] and not s["stable"]
    hull = clip_box(planes, _slice(camera, d0, d1), rlo, rhi)
    if len(hull) < 4:
        return None
    zs = hull @ Mv0[2, :3]
    zmax = cast_near  # USE_DEPTH_CLAMP false: the near plane at the casters
    zmin = max(float(zs.min()), cast_far)  # far_uses_shadowcasters
    Mv = light_view(direction, direction * -zmax)
    zfar = zmax - zmin
    if zfar <= 0:
        return None
    sphere_r, centre = 0.0, None
    if s["stable"]:
        rc = _corners(rlo, rhi)
        r_rec = float(np.max(np.linalg.norm(rc - rc.mean(axis=0), axis=1)))
        sl = _slice(camera, d0, d1)
        centre = sl.mean(axis=0)
        sphere_r = float(np.max(np.linalg.norm(sl - centre, axis=1)))
        if r_rec < sphere_r:
            sphere_r, hull = 0.0, rc
    Mp = np.eye(4)
    Mp[2, 2], Mp[2, 3] = -2.0 / zfar, -1.0  # directionalLightFrustum(0, zfar)
    L = np.eye(4)
    W = Wp = np.eye(4)
    if use_lispsm:
        fwd_ls = Mv[:3, :3] @ np.asarray(camera.forward, np.float64)
        if abs(fwd_ls[2]) < 0.9997:
            vp = np.array([fwd_ls[0], fwd_ls[1], 0.0]) / np.linalg.norm(fwd_ls[:2])
            L[0, :3], L[1, :3] = np.cross(vp, [0.0, 0.0, 1.0]), vp
        W, Wp = _lispsm(camera, s, L @ Mp @ Mv, hull, direction, far)
    LMpMv = L @ Mp @ Mv
    WLMpMv = W @ LMpMv
    if s["stable"]:
        if sphere_r > 0:
            s2 = np.full(2, 1.0 / sphere_r)
            o2 = _project(LMpMv, centre[None])[0, :2]
        else:
            lo2, hi2 = _bounds2d(LMpMv, hull)
            s2 = 2.0 / (hi2 - lo2)
            o2 = (hi2 + lo2) * 0.5
            s2 = 1.0 / (np.ceil(1.0 / (s2 * STABLE_QUANTUM)) * STABLE_QUANTUM)
    else:
        lo2, hi2 = _bounds2d(WLMpMv, hull)
        # intersectWithShadowCasters (focus_shadowcasters): the casters' box clipped by the light frustum
        proj = _focus(2.0 / (hi2 - lo2), -(2.0 / (hi2 - lo2)) * (hi2 + lo2) * 0.5) @ WLMpMv
        ndc = np.array([[1 if k & 1 else -1, 1 if k & 2 else -1, -1 if k & 4 else 1] for k in range(8)], float)
        cast = clip_box(_planes(proj), _project(np.linalg.inv(proj), ndc), rlo, rhi)
        if len(cast):
            clo, chi = _bounds2d(WLMpMv, cast)
            lo2, hi2 = np.maximum(lo2, clo), np.minimum(hi2, chi)
        if np.any(lo2 >= hi2):
            return None
        s2, o2 = 2.0 / (hi2 - lo2), (hi2 + lo2) * 0.5
    o2 = -s2 * o2
    if s["stable"]:  # snapLightFrustum: the casters' centre on a 2-texel grid
        ls_origin = _project(_focus(s2, o2) @ LMpMv, (0.5 * (rlo + rhi))[None])[0, :2]
        o2 = o2 - np.fmod(ls_origin * (size - 2) * 0.5, 1.0) * 2.0 / (size - 2)
    F = _focus(s2, o2)
    projection = F @ W @ L @ Mp
    Mt = _texture_mapping(size)
    warped = bool(use_lispsm and Wp[3, 1] != 0.0)
    texel = texel_size(Mt @ projection @ Mv, Mt @ F, Wp, warped, size)
    # constantBias as a stored-depth shift: dD/dd = 1 / zfar (ortho), n / (y_c zfar) at the map's centre (LiSPSM)
    dDdd = 1.0 / zfar if not warped else Wp[0, 0] / ((-Wp[1, 3] / Wp[1, 1]) * zfar)
    smap = ShadowMap(Mv, projection, (size - 2, size - 2), (d0, d1), (0.0, zfar),
                     warp_kind="perspective" if warped else "none", snapped=bool(s["stable"]))
    smap.depth = {"mode": "hardware", "format": DEPTH_FORMAT, "chosen_by": "engine",
                  "hardware": {"constant": s["polygonOffsetConstant"] / UNORM16_STEPS + s["constantBias"] * dDdd,
                               "slope": 0.0, "normal_offset": 0.0, "slope_scaled": s["polygonOffsetSlope"],
                               "slope_clamp": 1.0}}
    return smap, texel


__all__ = ["ENGINE", "VERSION", "KNOBS", "validate", "effective", "faces", "fit", "scene_boxes", "splits",
           "light_view", "clip_box", "warp_frustum", "texel_size", "SHADOW_MAP_TYPE", "DEPTH_FORMAT"]
