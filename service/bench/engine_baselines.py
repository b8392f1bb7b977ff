"""What an engine user gets without the product, for `shadowopt bench engines` (issue 26's custom-matrix targets), as
ES modules of the emitted modules' contract (`export default function apply(ENGINE, ctx)`, service/emit.py):

- the engine's plain single shadow map fitted by hand to the scene: an orthographic light camera holding a tight box
  around the scene's vertices (`light_box`: the box in a light frame whose depth axis is the sun; the module takes
  the bounds of its 8 corners in the engine's own light view, whose x and y axes are the box's up to sign, both
  engines building it with world +Y as up), nearest-texel lookups (three.js BasicShadowMap, Babylon.js FILTER_NONE),
  and a grid of 3 constant biases (BIAS_TEXELS: 0.5, 1.5 and 4.5 texels' width of depth, as a fraction of the box's depth
  range, the unit both engines' bias is in) x 2 material sides (front faces only, both faces) in the light pass;
  the benchmark keeps the best of the 6 per sun;
- the engine's own cascades with its defaults, the shadow distance set to the camera's distance to the farthest point
  of the scene capped by its far plane (service.tune_score.scene_far) and the solution's map size: three.js's CSM
  addon through `tune`'s module writer (service/emit_tune_three.py), Babylon.js's CascadedShadowGenerator here
  (4 cascades, lambda 0.5, PCF, depthClamp, bias 5e-5: Lights/Shadows/cascadedShadowGenerator.pure.js), with
  cascade blending off (cascadeBlendPercentage 0) so each pixel reads one cascade.
"""
from __future__ import annotations

import json

import numpy as np

BIAS_TEXELS = (0.5, 1.5, 4.5)  # the constant bias in texel widths of depth (a user's 3 tries, light to heavy)
SIDES = ("front", "double")  # faces drawn into the map: three.js material.shadowSide, Babylon.js culling


def light_frame(direction) -> np.ndarray:
    """Rows x, y, z of a light frame: z along the light's travel, x = normalize(+Y x z) (three's Object3D.lookAt and
    Babylon's Matrix.LookAtLH both take world +Y as up; +Z as up when the sun is vertical)."""
    z = np.asarray(direction, np.float64)
    z = z / np.linalg.norm(z)
    up = np.array([0.0, 1.0, 0.0]) if abs(z[1]) < 0.999 else np.array([0.0, 0.0, 1.0])
    x = np.cross(up, z)
    x /= np.linalg.norm(x)
    return np.stack([x, np.cross(z, x), z])


def light_box(vertices, direction) -> tuple[np.ndarray, np.ndarray]:
    """The tight box around `vertices` (n, 3) in the light frame: its 8 world corners and its extents (width,
    height, depth in metres; depth along the light)."""
    R = light_frame(direction)
    p = np.asarray(vertices, np.float64) @ R.T
    lo, hi = p.min(axis=0), p.max(axis=0)
    corners = np.array([[a, b, c] for a in (lo[0], hi[0]) for b in (lo[1], hi[1]) for c in (lo[2], hi[2])]) @ R
    return corners, hi - lo


def grid(extents, size: int) -> list[dict]:
    """The hand settings: BIAS_TEXELS x SIDES, each bias a fraction of the box's depth range."""
    texel = float(max(extents[0], extents[1])) / size
    return [{"bias": k * texel / float(extents[2]), "bias_texels": k, "side": side}
            for k in BIAS_TEXELS for side in SIDES]


def _module(template: str, params: dict) -> str:
    return template.replace("@@PARAMS@@", json.dumps(params))


def three_plain_module(corners, size: int, setting: dict) -> str:
    """three.js r187: the light's own DirectionalLightShadow, its OrthographicCamera set to the box."""
    return _module(THREE_PLAIN, {"corners": np.asarray(corners).tolist(), "size": int(size), **setting})


def babylon_plain_module(corners, size: int, setting: dict) -> str:
    """Babylon.js 9.35: a ShadowGenerator whose light projection is OrthoOffCenterLH of the box (corners in
    Babylon's frame) through light.customProjectionMatrixBuilder."""
    return _module(BABYLON_PLAIN, {"corners": np.asarray(corners).tolist(), "size": int(size), **setting})


def babylon_cascades_module(size: int, shadow_max_z: float) -> str:
    """Babylon.js 9.35's CascadedShadowGenerator with its defaults, shadowMaxZ and mapSize set, blending off."""
    return _module(BABYLON_CSM, {"size": int(size), "shadowMaxZ": float(shadow_max_z)})


THREE_PLAIN = """// shadowopt bench engines: three.js's plain single shadow map fitted by hand (service/bench/engine_baselines.py)
const P = @@PARAMS@@;
export default function apply(THREE, ctx) {
	const { renderer, scene, light } = ctx;
	const saved = { type: renderer.shadowMap.type, enabled: renderer.shadowMap.enabled, castShadow: light.castShadow };
	renderer.shadowMap.enabled = true;
	renderer.shadowMap.type = THREE.BasicShadowMap;
	light.castShadow = true;
	const cam = light.shadow.camera;  // as LightShadow.updateMatrices places it each frame
	light.updateMatrixWorld(); light.target.updateMatrixWorld();
	cam.position.setFromMatrixPosition(light.matrixWorld);
	cam.lookAt(new THREE.Vector3().setFromMatrixPosition(light.target.matrixWorld));
	cam.updateMatrixWorld();
	const lo = [Infinity, Infinity, Infinity], hi = [-Infinity, -Infinity, -Infinity];
	for (const c of P.corners) {
		const v = new THREE.Vector3(c[0], c[1], c[2]).applyMatrix4(cam.matrixWorldInverse).toArray();
		for (let i = 0; i < 3; i++) { lo[i] = Math.min(lo[i], v[i]); hi[i] = Math.max(hi[i], v[i]); }
	}
	cam.left = lo[0]; cam.right = hi[0]; cam.bottom = lo[1]; cam.top = hi[1]; cam.near = -hi[2]; cam.far = -lo[2];
	cam.updateProjectionMatrix();
	light.shadow.mapSize.set(P.size, P.size);
	light.shadow.bias = -P.bias;  // three adds it to the receiver's depth: negative moves it towards the light
	light.shadow.normalBias = 0;
	const side = P.side === "front" ? THREE.FrontSide : THREE.DoubleSide;
	const materials = [];
	const meshes = [];
	scene.traverse((o) => {
		if (!o.isMesh) return;
		meshes.push([o, o.castShadow, o.receiveShadow]);
		o.castShadow = true; o.receiveShadow = true;
		for (const m of Array.isArray(o.material) ? o.material : [o.material]) {
			materials.push([m, m.shadowSide]); m.shadowSide = side; m.needsUpdate = true;
		}
	});
	return {
		dispose() {
			renderer.shadowMap.type = saved.type; renderer.shadowMap.enabled = saved.enabled;
			light.castShadow = saved.castShadow; light.shadow.bias = 0;
			for (const [m, s] of materials) { m.shadowSide = s; m.needsUpdate = true; }
			for (const [o, c, r] of meshes) { o.castShadow = c; o.receiveShadow = r; }
		},
	};
}
"""

BABYLON_PLAIN = """// shadowopt bench engines: Babylon.js's plain single shadow map fitted by hand (service/bench/engine_baselines.py)
const P = @@PARAMS@@;
export default function apply(BABYLON, ctx) {
	const { engine, scene, light } = ctx;
	const corners = P.corners.map((c) => new BABYLON.Vector3(c[0], c[1], c[2]));
	const savedBuilder = light.customProjectionMatrixBuilder;
	light.customProjectionMatrixBuilder = (view, renderList, result) => {
		const lo = [Infinity, Infinity, Infinity], hi = [-Infinity, -Infinity, -Infinity];
		for (const c of corners) {
			const v = BABYLON.Vector3.TransformCoordinates(c, view);
			const a = [v.x, v.y, v.z];
			for (let i = 0; i < 3; i++) { lo[i] = Math.min(lo[i], a[i]); hi[i] = Math.max(hi[i], a[i]); }
		}
		BABYLON.Matrix.OrthoOffCenterLHToRef(lo[0], hi[0], lo[1], hi[1], lo[2], hi[2], result, engine.isNDCHalfZRange);
	};
	light.forceProjectionMatrixCompute();
	const sg = new BABYLON.ShadowGenerator(P.size, light);
	sg.filter = BABYLON.ShadowGenerator.FILTER_NONE;
	sg.bias = P.bias;  // added to the caster's stored depth, a fraction of the box's depth range
	sg.normalBias = 0;
	const meshes = ctx.meshes || scene.meshes;
	for (const m of meshes) { sg.addShadowCaster(m, false); m.receiveShadows = true; }
	const cull = P.side === "front";  // front faces only (a material's backFaceCulling) or both, in the light pass only
	sg.onBeforeShadowMapRenderMeshObservable.add(() => engine.setState(cull, 0, true));
	return {
		update() { light.forceProjectionMatrixCompute(); sg.getShadowMap().resetRefreshCounter(); },
		dispose() {
			sg.dispose();
			light.customProjectionMatrixBuilder = savedBuilder;
			for (const m of meshes) m.receiveShadows = false;
			light.forceProjectionMatrixCompute();
		},
		shadowGenerator: sg,
	};
}
"""

BABYLON_CSM = """// shadowopt bench engines: Babylon.js's own cascades with its defaults (service/bench/engine_baselines.py)
const P = @@PARAMS@@;
export default function apply(BABYLON, ctx) {
	const { scene, camera, light } = ctx;
	const csm = new BABYLON.CascadedShadowGenerator(P.size, light, undefined, camera);
	csm.shadowMaxZ = P.shadowMaxZ;  // the camera's distance to the scene's farthest point, capped by its far plane
	csm.cascadeBlendPercentage = 0;  // each pixel reads one cascade
	const meshes = ctx.meshes || scene.meshes;
	for (const m of meshes) { csm.addShadowCaster(m, false); m.receiveShadows = true; }
	return {
		dispose() { csm.dispose(); for (const m of meshes) m.receiveShadows = false; },
		shadowGenerator: csm,
	};
}
"""
