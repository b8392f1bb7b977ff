// Babylon.js CascadedShadowGenerator settings tuned by `shadowopt tune --engine babylon --emit`
// (service/emit_tune_babylon.py). Import it as it is: `import apply from "./this.js"; const s = apply(BABYLON, ctx);
// ... s.update(); ... s.dispose();`. BABYLON: a namespace holding CascadedShadowGenerator and ShadowGenerator (the
// UMD global `BABYLON`, or `{ CascadedShadowGenerator, ShadowGenerator }` imported from @babylonjs/core);
// ctx = { engine, scene, camera, light, meshes }: `camera` the camera the settings were tuned for (its minZ, maxZ and
// fov as in the rig), `light` a DirectionalLight already pointed along the rig's sun (in the scene's frame; the
// module does not move it), `meshes` the meshes that cast and receive (Babylon fits each cascade's depth range to
// their bounding box). Written for @babylonjs/core @@BABYLON_VERSION@@; the files named below are that release's.
//
// What it sets, and where Babylon.js applies it:
// - a CascadedShadowGenerator (Lights/Shadows/cascadedShadowGenerator.pure.js) of mapSize for `light` and `camera`:
//   numCascades, lambda, stabilizeCascades, depthClamp, shadowMaxZ (its setter ignores a value beyond camera.maxZ),
//   cascadeBlendPercentage 0 (no blending, as the tuning scored), bias and normalBias (ShadowGenerator), and the
//   filter (FILTER_NONE: one nearest texel, the test the tuning scored);
// - every mesh of ctx.meshes a shadow caster (addShadowCaster) and receiver (receiveShadows = true), and its
//   material's backFaceCulling off (the shadow pass draws both faces, as the tuning scored).
// dispose() disposes the generator and restores every property it changed (receiveShadows, backFaceCulling).
// update() does nothing: Babylon refits the cascades every frame from the camera it was given.

const TUNED = @@TUNED@@;

export const tuned = TUNED;

export default function apply(BABYLON, ctx) {
	const { camera, light } = ctx;
	const { CascadedShadowGenerator, ShadowGenerator } = BABYLON;
	if (!CascadedShadowGenerator || !ShadowGenerator) throw new Error("shadowopt: pass a BABYLON namespace holding " +
		"CascadedShadowGenerator and ShadowGenerator (@babylonjs/core)");
	if (!camera || !light) throw new Error("shadowopt: pass the camera as ctx.camera and the DirectionalLight as ctx.light");
	const saved = [];
	const set = (obj, key, value) => {
		saved.push([obj, key, obj[key]]);
		obj[key] = value;
	};
	const s = TUNED.settings;
	const csm = new CascadedShadowGenerator(s.mapSize, light, undefined, camera);
	csm.numCascades = s.numCascades;
	csm.lambda = s.lambda;
	csm.stabilizeCascades = s.stabilizeCascades;
	csm.depthClamp = s.depthClamp;
	csm.cascadeBlendPercentage = 0;
	csm.shadowMaxZ = s.shadowMaxZ;
	csm.filter = ShadowGenerator["FILTER_" + (s.filter === "NONE" ? "NONE" : "PCF")];
	csm.bias = s.bias;
	csm.normalBias = s.normalBias;
	for (const mesh of ctx.meshes || []) {
		csm.addShadowCaster(mesh);
		set(mesh, "receiveShadows", true);
		if (mesh.material) set(mesh.material, "backFaceCulling", false);
	}
	const dispose = () => {
		csm.dispose();
		for (let i = saved.length - 1; i >= 0; i--) {
			const [obj, key, value] = saved[i];
			obj[key] = value;
		}
		saved.length = 0;
	};
	return { update() {}, dispose, shadowGenerator: csm };
}
