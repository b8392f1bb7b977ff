"""Babylon.js 9.35's CascadedShadowGenerator (@babylonjs/core Lights/Shadows/cascadedShadowGenerator.pure.js, WebGL2
engine) as pure math: the cascades it fits for one directional light and one camera pose, from the options its users
set (solvers.engine_fits: the interface; ../shared/reference/engine-settings.md §2, checked against the files of
@babylonjs/core@9.35.0 as `make setup` installs them under out/web/node_modules/@babylonjs/core/).

Steps, each as the generator does it (method in the comment at each step below), in Babylon's left-handed frame (the
`babylon` preset: x -> -x, solvers.conventions.ENGINE_PRESETS), then back to the world frame:
1. breaks (_splitFrustum): n = camera.minZ, f = camera.maxZ, R = f - n; maxD = min((shadowMaxZ - n) / R, 1) when
   n <= shadowMaxZ < f, else 1 (the shadowMaxZ setter also ignores a value beyond camera.maxZ: it keeps the camera's
   far plane); minZ = n, maxZ = n + maxD R; d_i = lambda (log_i - uni_i) + uni_i with log_i = minZ (maxZ / minZ)^p,
   uni_i = minZ + (maxZ - minZ) p, p = (i + 1) / N; break_i = (d_i - n) / R, prevBreak_0 = 0.
2. slices (_computeFrustumInWorldSpace): the camera frustum's 8 corners, each near -> far edge lerped at prevBreak
   and break.
3. extents (_computeCascadeFrustum): centre = mean of the 8 corners; stabilizeCascades: r = ceil(16 max |corner -
   centre|) / 16, extents +-r; else the corners' box in LookAtLH(centre, centre + D, +Y).
4. matrices (_computeMatrices): D normalized (z = 1e-13 when D is vertical); the light camera at centre + D minExt.z
   with LookAtLH(pos, centre, +Y); view z range [0, maxExt.z - minExt.z], tightened to the casters' box when one is
   given (depthClamp, not PCSS: maxZ = min(maxZ, castersMaxZ), minZ = max(0, castersMinZ), maxZ >= minZ + 1; no
   depthClamp: minZ = min(0, castersMinZ), maxZ = min(maxZ, castersMaxZ)); P = OrthoOffCenterLH(extents, minZ, maxZ)
   with clip z in [-1, 1]; the world origin projected by P V, times mapSize / 2, rounded in x and y, and P translated
   by the difference times 2 / mapSize.
5. selection (shadowsFragmentFunctions.js / lightFragment.js, CSM): cascade i for view depths up to d_i, the first
   from the camera's near plane; past d_{N-1} lit (when shadowMaxZ holds). Blending (cascadeBlendPercentage) is not
   emulated: the emitted settings turn it off (0).
6. bias (shadowMapVertexMetric.js, shadowMapFragment.js): added to the caster's stored depth ([0, 1] over the
   cascade's z range), before the map's rounding (constant_side caster, solvers.engine_depth_test.CONSTANT_SIDES);
   1.5 x bias with PCF and depthClamp (Babylon's default CSM path: the vertex shader adds bias w to clip z, half a
   bias in window depth, then the fragment writes (zSM + 1) / 2 + bias), 1 x with FILTER_NONE (the colour-metric path),
   0.5 x with PCF without depthClamp.

Approximate: the casters' box (step 4) is Babylon's bounding box of its render list, which `fit` takes only when
given (casters_box); without it the z range is the slice box's. PCF's 3 x 3 filtered lookup is scored as one nearest
texel and its depth texture's format taken as unorm24 (not verified in the engine); normalBias (casters moved
inward) has no model in the product's depth test and is offered at 0 only; the light pass's rasterization is the
product's texel-centre ray.
"""
from __future__ import annotations

import math

import numpy as np

from ..cameras import Camera
from ..frames import engine_from_world
from ..lights import DirectionalLight
from ..shadow_map import ShadowMap
from .knobs import Knob, validate_settings

ENGINE = "babylon"
VERSION = "9.35.0"  # npm @babylonjs/core; Makefile's Babylon.js rule pins it
SHADOW_MAP_TYPE = "FILTER_NONE"  # nearest-texel lookups and one comparison, the test the emulation scores
DEPTH_FORMAT = "float16"  # FILTER_NONE: a half-float colour target (shadowGenerator.js _createInstance)
MIN_CASCADES, MAX_CASCADES = 2, 4  # CascadedShadowGenerator.MIN_CASCADES_COUNT / MAX_CASCADES_COUNT
MIRROR = engine_from_world(("-x", "y", "z"), 1.0)  # the babylon preset's frame (its own inverse)
FLIP_Z = np.diag([1.0, 1.0, -1.0, 1.0])  # a left-handed view (looks down +Z) -> the product's (looks down -Z)

KNOBS: dict[str, Knob] = {
    "numCascades": Knob(4, "int", (1, 8), "number of cascades, layers of one map array (numCascades setter: clamped to "
                        "[2, 4], so 1 means 2 and 5..8 mean 4)"),
    "lambda": Knob(0.5, "float", (0.0, 1.0), "split blend: 0 uniform, 1 logarithmic (_splitFrustum)"),
    "shadowMaxZ": Knob(1e7, "float", (0.01, 1e7), "the shadowed view depth (_splitFrustum); the setter ignores a value "
                       "beyond the camera's far plane or before its near plane and keeps camera.maxZ (the default here: "
                       "larger than any far plane)"),
    "stabilizeCascades": Knob(False, "bool", (False, True), "a bounding sphere per cascade instead of a box "
                              "(_computeCascadeFrustum)"),
    "depthClamp": Knob(True, "bool", (False, True), "casters pancaked onto each cascade's near plane, which lets it "
                       "start at the casters (_computeMatrices); with PCF it makes the bias count 1.5 times"),
    "filter": Knob("PCF", "choice", ("PCF", "NONE"), "ShadowGenerator.FILTER_PCF (the CSM default: "
                   "usePercentageCloserFiltering) or FILTER_NONE (nearest texel); PCF is scored as one nearest texel"),
    "bias": Knob(0.00005, "float", (0.0, 0.05), "added to the caster's stored depth, a fraction of the cascade's z range "
                 "(shadowMapVertexMetric.js); x 1.5 with PCF and depthClamp"),
    "normalBias": Knob(0.0, "float", (0.0, 0.0), "moves casters inward along their normal "
                       "(shadowMapVertexNormalBias.js); not emulated: 0 only"),
    "mapSize": Knob(1024, "int", (16, 16384), "each cascade's map side in texels (the constructor's mapSize)"),
}


def validate(settings: dict | None) -> dict:
    """Settings checked and completed with KNOBS' defaults (ValueError naming the field otherwise)."""
    return validate_settings(ENGINE, KNOBS, settings)


def effective(settings: dict, camera: Camera | None = None) -> dict:
    """What the generator holds: numCascades clamped to [2, 4]; shadowMaxZ = camera.maxZ unless within the camera's
    [near, far] (the setter's early return)."""
    out = dict(settings)
    out["numCascades"] = min(max(int(out["numCascades"]), MIN_CASCADES), MAX_CASCADES)
    if camera is not None and not camera.near <= out["shadowMaxZ"] <= camera.far:
        out["shadowMaxZ"] = float(camera.far)
    return out


def faces(settings: dict) -> str:
    """The faces drawn into the maps: both (the emitted settings turn culling off in the shadow pass)."""
    return "both"


def pancakes(settings: dict) -> bool:
    """Whether casters in front of a cascade's near plane are pancaked onto it: with depthClamp (_computeMatrices)."""
    return bool(settings["depthClamp"])


def bias_factor(settings: dict) -> float:
    """How many times `bias` reaches the stored depth (module doc, step 6)."""
    if settings["filter"] == "PCF":
        return 1.5 if settings["depthClamp"] else 0.5
    return 1.0


def breaks(camera: Camera, settings: dict) -> tuple[np.ndarray, np.ndarray]:
    """_splitFrustum: (prevBreak, break) per cascade as fractions of the camera range, and the split depths d_i."""
    s = effective(settings, camera)
    n, f = float(camera.near), float(camera.far)
    R = f - n
    max_d = min((s["shadowMaxZ"] - n) / R, 1.0) if n <= s["shadowMaxZ"] < f else 1.0
    lo, hi = n, n + max_d * R
    p = np.arange(1, s["numCascades"] + 1) / s["numCascades"]
    log, uni = lo * (hi / lo) ** p, lo + (hi - lo) * p
    d = s["lambda"] * (log - uni) + uni
    brk = (d - n) / R
    return np.concatenate([[0.0], brk[:-1]]), brk, d


def _look_at_lh(eye: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Matrix.LookAtLHToRef(eye, target, +Y) as a column-vector matrix (Maths/math.vector.pure.js)."""
    z = (target - eye) / np.linalg.norm(target - eye)
    x = np.cross([0.0, 1.0, 0.0], z)
    x = x / np.linalg.norm(x) if np.dot(x, x) > 0 else np.array([1.0, 0.0, 0.0])
    y = np.cross(z, x)
    y /= np.linalg.norm(y)
    m = np.eye(4)
    m[:3, :3] = np.stack([x, y, z])
    m[:3, 3] = -m[:3, :3] @ eye
    return m


def _ortho_lh(l: float, r: float, b: float, t: float, zn: float, zf: float) -> np.ndarray:
    """Matrix.OrthoOffCenterLHToRef with clip z in [-1, 1] (WebGL): z_ndc = 2 (z - zn) / (zf - zn) - 1."""
    m = np.eye(4)
    m[0, 0], m[1, 1], m[2, 2] = 2 / (r - l), 2 / (t - b), 2 / (zf - zn)
    m[0, 3], m[1, 3], m[2, 3] = (l + r) / (l - r), (t + b) / (b - t), -(zf + zn) / (zf - zn)
    return m


def _frustum_corners(camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """The camera frustum's near and far corners (4 x 3 each, same order) in Babylon's frame."""
    th = camera.tan_half_fov_y
    tw = th * camera.aspect
    sx, sy = np.array([-1.0, 1.0, 1.0, -1.0]), np.array([1.0, 1.0, -1.0, -1.0])
    to_world = np.linalg.inv(camera.view_matrix())
    out = []
    for d in (camera.near, camera.far):
        pts = np.stack([sx * tw * d, sy * th * d, np.full(4, -d), np.ones(4)], axis=1)
        out.append((pts @ (MIRROR @ to_world).T)[:, :3])
    return out[0], out[1]


def fit(camera: Camera, light: DirectionalLight, settings: dict, casters_box: tuple | None = None) -> list[ShadowMap]:
    """The generator's cascades for this camera pose and light (module doc), with validated settings; casters_box:
    the casters' world (min, max) corners, Babylon's render-list box (step 4), or None."""
    s = effective(validate(settings), camera)
    size = int(s["mapSize"])
    D = MIRROR[:3, :3] @ np.asarray(light.direction, float)
    D = D / np.linalg.norm(D)
    if abs(D[1]) == 1.0:
        D[2] = 1e-13  # _computeMatrices: "avoid perfectly perpendicular light"
    prev, brk, d = breaks(camera, s)
    near_c, far_c = _frustum_corners(camera)
    box = None
    if casters_box is not None:
        lo, hi = (np.asarray(v, float) for v in casters_box)
        box = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
        box = box @ MIRROR[:3, :3].T
    depth = {"mode": "hardware", "format": DEPTH_FORMAT if s["filter"] == "NONE" else "unorm24", "chosen_by": "engine",
             "hardware": {"constant": float(s["bias"]) * bias_factor(s), "slope": 0.0, "normal_offset": 0.0,
                          "slope_scaled": 0.0, "slope_clamp": 1.0, "constant_side": "caster"}}
    maps = []
    for i in range(s["numCascades"]):
        edge = far_c - near_c
        corners = np.vstack([near_c + edge * prev[i], near_c + edge * brk[i]])  # _computeFrustumInWorldSpace
        centre = corners.mean(axis=0)  # _computeCascadeFrustum
        if s["stabilizeCascades"]:
            r = math.ceil(float(np.max(np.linalg.norm(corners - centre, axis=1))) * 16) / 16
            mn, mx = np.full(3, -r), np.full(3, r)
        else:
            v = _look_at_lh(centre, centre + D)
            pts = corners @ v[:3, :3].T + v[:3, 3]
            mn, mx = pts.min(axis=0), pts.max(axis=0)
        view = _look_at_lh(centre + D * mn[2], centre)  # _computeMatrices
        z0, z1 = 0.0, float(mx[2] - mn[2])
        if box is not None:
            bz = box @ view[2, :3] + view[2, 3]
            if not bz.min() > z1:
                if s["depthClamp"]:
                    z1 = min(z1, float(bz.max()))
                    z0 = max(z0, float(bz.min()))
                    z1 = max(z0 + 1.0, z1)
                else:
                    z0, z1 = min(z0, float(bz.min())), min(z1, float(bz.max()))
        proj = _ortho_lh(mn[0], mx[0], mn[1], mx[1], z0, z1)
        o = (proj @ view)[:3, 3] * size / 2  # the world origin through P V (w = 1), in half-texels
        snap = np.eye(4)
        snap[0, 3], snap[1, 3] = (np.floor(o[:2] + 0.5) - o[:2]) * 2 / size  # Math.round
        proj = snap @ proj
        split = (float(camera.near) if i == 0 else float(d[i - 1]), float(d[i]))
        smap = ShadowMap(FLIP_Z @ view @ MIRROR, proj @ FLIP_Z, (size, size), split, (z0, z1), snapped=True)
        smap.depth = {k: (dict(v) if isinstance(v, dict) else v) for k, v in depth.items()}
        maps.append(smap)
    return maps
