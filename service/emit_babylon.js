// A shadowopt solution for Babylon.js, written by `shadowopt optimize --emit` (service/emit_babylon.py).
// Import it as it is: `import apply from "./this.js"; const s = apply(BABYLON, ctx); ... s.dispose();`
// ctx = { engine, scene, camera, light, meshes }: `light` a BABYLON.DirectionalLight already pointed along the rig's
// sun (its direction in this file's frame below), with no shadow generator yet; `meshes` the casters and receivers.
// Written for Babylon.js @@BABYLON_VERSION@@ (@babylonjs/core, WebGL2 engine, left-handed scene, no reverse depth
// buffer); every Babylon.js file named below is in that package.
//
// What it installs, and where Babylon.js applies it:
// - one ShadowGenerator of the solution's map size, FILTER_NONE: nearest-texel lookups of the map
//   (Lights/Shadows/shadowGenerator.js _applyFilterValues: NEAREST_SAMPLINGMODE) and one comparison per pixel
//   (Shaders/ShadersInclude/shadowsFragmentFunctions.js computeShadow: shadowed iff the receiver's metric exceeds
//   the stored one). Its map is half float where the device renders half floats (_createInstance), the format the
//   bias was fitted for.
// - the map's matrix: light.customProjectionMatrixBuilder returns view⁻¹ · T for the view Babylon builds itself
//   (getTransformMatrix: Matrix.LookAtLHToRef from the light's position and direction, then view · projection), so
//   the shadow transform is exactly T, the solution's projection · view with the linear depth in its depth row
//   (service/emit_babylon.py says why: Babylon compares (clip z + 1) / 2 before the divide by w).
// - the bias: shadowGenerator.bias = the depth block's constant, added to the casters' stored metric
//   (Shaders/ShadersInclude/shadowMapVertexMetric.js); normalBias 0 (it would move casters, not receivers).
// - both faces of every caster in the map: culling off for each mesh's shadow draw only
//   (onBeforeShadowMapRenderMeshObservable runs after the generator's own engine.setState), the camera's pass
//   untouched.
// - depth clamping in the light pass where the browser has EXT_depth_clamp (casters in front of the map's near plane
//   store a metric below 0 and shadow what lies behind them, as the solution assumes), around the map's render.
// - every ctx mesh casting (the map's renderList) and receiving (mesh.receiveShadows).
// dispose() restores what it changed (the light's customProjectionMatrixBuilder, the meshes' receiveShadows) and
// disposes its generator. update() asks for the map to be redrawn.

const SOLUTION = @@SOLUTION@@;

export const solution = SOLUTION;

export default function apply(BABYLON, ctx) {
	const { engine, scene, light } = ctx;
	if (!light || typeof light.getClassName !== "function" || light.getClassName() !== "DirectionalLight") {
		throw new Error("shadowopt: ctx.light must be a BABYLON.DirectionalLight (this solution is for a directional light)");
	}
	if (scene.useRightHandedSystem) {
		throw new Error("shadowopt: the matrices are for Babylon's default left-handed frame (output.engine babylon); " +
			"this scene has useRightHandedSystem = true");
	}
	if (engine.isNDCHalfZRange || engine.useReverseDepthBuffer || scene.floatingOriginMode) {
		throw new Error("shadowopt: written for the WebGL2 engine with clip z in [-1, 1], no reverse depth buffer and " +
			"no floating origin");
	}
	if (light.getShadowGenerator && light.getShadowGenerator()) {
		throw new Error("shadowopt: ctx.light already has a shadow generator; dispose it first (the module makes its own)");
	}
	const saved = [];
	const set = (obj, key, value) => {
		saved.push([obj, key, Object.prototype.hasOwnProperty.call(obj, key), obj[key]]);
		obj[key] = value;
	};
	const restore = () => {
		for (let i = saved.length - 1; i >= 0; i--) {
			const [obj, key, own, value] = saved[i];
			if (own || value !== undefined) obj[key] = value; else delete obj[key];  // an accessor (receiveShadows) is set back
		}
		saved.length = 0;
	};
	if (SOLUTION.maps.length === 0) {  // shadow "none": no visible surface faces the light; it casts no shadow
		return { update() {}, dispose: restore, shadowGenerator: null };
	}
	const map = SOLUTION.maps[0];
	const d = SOLUTION.direction;
	if (d) {
		const dir = light.direction.clone().normalize();
		const cos = (dir.x * d[0] + dir.y * d[1] + dir.z * d[2]) / Math.hypot(d[0], d[1], d[2]);
		if (cos < Math.cos(Math.PI / 180)) {
			console.warn("shadowopt: ctx.light points more than 1 degree away from the rig's sun; the map follows the " +
				"solution, the lighting follows the light");
		}
	}
	const maxSize = engine.getCaps().maxRenderTextureSize;
	if (map.resolution > maxSize) {
		console.warn(`shadowopt: the map is ${map.resolution} texels wide, this engine renders at most ${maxSize}`);
	}

	const T = BABYLON.Matrix.FromArray(map.transform);  // column-major, as Matrix.m holds it
	const viewInverse = new BABYLON.Matrix();
	set(light, "customProjectionMatrixBuilder", (view, renderList, result) => {
		view.invertToRef(viewInverse);
		viewInverse.multiplyToRef(T, result);  // Babylon then forms view · result = T (row-vector order)
	});
	light.forceProjectionMatrixCompute();

	const sg = new BABYLON.ShadowGenerator(map.resolution, light);
	sg.filter = BABYLON.ShadowGenerator.FILTER_NONE;
	sg.bias = map.bias;
	sg.normalBias = 0;
	sg.forceBackFacesOnly = false;
	const meshes = ctx.meshes || scene.meshes;
	for (const mesh of meshes) {
		sg.addShadowCaster(mesh, false);
		set(mesh, "receiveShadows", true);
	}
	sg.onBeforeShadowMapRenderMeshObservable.add(() => engine.setState(false, 0, true));  // both faces, shadow pass only

	const canvas = engine.getRenderingCanvas && engine.getRenderingCanvas();
	const gl = canvas && engine.webGLVersion >= 2 ? canvas.getContext("webgl2") : null;  // the engine's own context
	const clamp = gl ? gl.getExtension("EXT_depth_clamp") : null;
	const shadowMap = sg.getShadowMap();
	if (clamp) {
		shadowMap.onBeforeRenderObservable.add(() => gl.enable(clamp.DEPTH_CLAMP_EXT));
		shadowMap.onAfterRenderObservable.add(() => gl.disable(clamp.DEPTH_CLAMP_EXT));
	}
	const halfFloat = shadowMap.textureType === BABYLON.Constants.TEXTURETYPE_HALF_FLOAT;
	if (!halfFloat) {
		console.warn("shadowopt: Babylon made this shadow map without half floats; the bias was fitted for a half-float map");
	}
	return {
		update() { light.forceProjectionMatrixCompute(); shadowMap.resetRefreshCounter(); },
		dispose() { sg.dispose(); restore(); light.forceProjectionMatrixCompute(); },
		shadowGenerator: sg,
		depthClamp: Boolean(clamp),
		halfFloat,
	};
}
