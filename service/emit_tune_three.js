// three.js CSM settings tuned by `shadowopt tune --engine three --emit` (service/emit_tune_three.py).
// Import it as it is: `import apply from "./this.js"; const s = apply(THREE, ctx); ... s.update(); ... s.dispose();`
// ctx = { renderer, scene, camera, light, materials, CSM }: `CSM` three's addon class (three/addons/csm/CSM.js),
// `camera` the PerspectiveCamera the settings were tuned for (its near, far, fov and aspect as in the rig),
// `light` a THREE.DirectionalLight (its colour and intensity are copied; it is hidden while CSM lights the scene),
// `materials` every mesh material. Written for three.js @@THREE_VERSION@@ (WebGLRenderer); the files named below
// are that release's.
//
// What it sets, and where three.js applies it:
// - a CSM instance (examples/jsm/csm/CSM.js) from the tuned options: cascades, mode, maxFar, shadowMapSize,
//   shadowBias, lightNear, lightFar, lightMargin, the rig's sun as lightDirection; fade off (CSM.fade);
// - each cascade light's shadow.normalBias (not a CSM option: world metres along the receiver's normal,
//   ShaderChunk/shadowmap_vertex.glsl.js);
// - nearest-texel lookups (renderer.shadowMap.type = BasicShadowMap), the test the tuning scored;
// - material.shadowSide (the tuned faces) and csm.setupMaterial on every material; every mesh casts and receives.
// dispose() restores every property it changed (the renderer's shadow map type and enabled flag, the light's
// visibility, the materials' shadowSide, defines and onBeforeCompile, the meshes' castShadow and receiveShadow,
// the shader chunks CSM replaces) and removes CSM's lights. update() calls csm.update() (each frame, after the
// camera moved and before renderer.render).

const TUNED = @@TUNED@@;

export const tuned = TUNED;

export default function apply(THREE, ctx) {
	const { renderer, scene, camera, light, CSM } = ctx;
	const saved = [];
	const set = (obj, key, value) => {
		saved.push([obj, key, Object.prototype.hasOwnProperty.call(obj, key), obj[key]]);
		obj[key] = value;
	};
	if (!CSM || !camera) throw new Error("shadowopt: pass three's CSM addon class (three/addons/csm/CSM.js) as ctx.CSM " +
		"and the camera as ctx.camera");
	const s = TUNED.settings;
	set(renderer.shadowMap, "enabled", true);
	set(renderer.shadowMap, "type", THREE[TUNED.shadow_map_type]);
	for (const c of ["lights_fragment_begin", "lights_pars_begin"]) set(THREE.ShaderChunk, c, THREE.ShaderChunk[c]);
	const d = TUNED.direction;
	const csm = new CSM({ camera, parent: scene, cascades: s.cascades, mode: s.mode, maxFar: s.maxFar,
		shadowMapSize: s.shadowMapSize, shadowBias: s.shadowBias, lightNear: s.lightNear, lightFar: s.lightFar,
		lightMargin: s.lightMargin, lightDirection: new THREE.Vector3(d[0], d[1], d[2]).normalize(),
		lightIntensity: light ? light.intensity : 3 });
	csm.fade = s.fade;
	csm.lights.forEach((l) => {
		if (light) { l.color.copy(light.color); l.intensity = light.intensity; }
		l.shadow.normalBias = s.shadowNormalBias;
	});
	if (light) set(light, "visible", false);
	const materials = new Set(ctx.materials || []);
	scene.traverse((o) => {
		if (!o.isMesh) return;
		set(o, "castShadow", true);
		set(o, "receiveShadow", true);
		for (const m of [].concat(o.material)) if (m) materials.add(m);
	});
	for (const m of materials) {
		set(m, "shadowSide", THREE[s.shadowSide]);
		set(m, "onBeforeCompile", m.onBeforeCompile);
		set(m, "defines", { ...(m.defines || {}) });
		csm.setupMaterial(m);
		m.needsUpdate = true;
	}
	csm.update();
	const dispose = () => {
		for (const l of csm.lights) l.shadow.dispose();
		csm.dispose();
		csm.remove();
		for (let i = saved.length - 1; i >= 0; i--) {
			const [obj, key, own, value] = saved[i];
			if (own) obj[key] = value; else delete obj[key];
		}
		saved.length = 0;
		for (const m of materials) m.needsUpdate = true;
	};
	return { update() { csm.update(); }, dispose, csm };
}
