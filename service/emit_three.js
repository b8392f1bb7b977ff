// A shadowopt solution for three.js, written by `shadowopt optimize --emit` (service/emit_three.py).
// Import it as it is: `import apply from "./this.js"; const s = apply(THREE, ctx); ... s.dispose();`
// ctx = { renderer, scene, camera, light, materials, CSM }: `light` a THREE.DirectionalLight already pointed along
// the rig's sun, `materials` every mesh material. Written for three.js @@THREE_VERSION@@ (WebGLRenderer without
// reversedDepthBuffer); every three.js file named below is in that release's src/.
//
// What it installs, and where three.js applies it:
// - the map's view and projection, exactly: the shadow's updateMatrices (lights/LightShadow.js, called once per
//   frame by renderers/webgl/WebGLShadowMap.js) is replaced by one that copies them into the shadow camera, sets
//   shadow.matrix to the solution's texture_matrix (the S · P · V that LightShadow builds itself) and the culling
//   frustum to P · V. A warped (perspective) projection needs nothing more: the lookup divides by w
//   (ShaderChunk/shadowmap_pars_fragment.glsl.js, getShadow: shadowCoord.xyz /= shadowCoord.w).
// - the receiver's constant: three adds shadow.bias to the receiver's window depth before the test
//   (getShadow: shadowCoord.z += shadowBias; shadowed iff it exceeds the stored depth), so bias = -constant.
// - the normal offset: shadow.normalBias moves the receiver along its world normal before the lookup, in world
//   units (ShaderChunk/shadowmap_vertex.glsl.js: worldPosition + shadowWorldNormal * shadowNormalBias).
// - the casters' slope-scaled offset: a customDepthMaterial per mesh with polygonOffset (factor slope_scaled,
//   units 0), since the depth pass takes the object's customDepthMaterial or its own MeshDepthMaterial and copies
//   no polygonOffset from the mesh's material (WebGLShadowMap.js getDepthMaterial); only when slope_scaled > 0.
//   WebGL has no polygon-offset clamp in three.js: a solution with slope_clamp < 1 is refused when emitting.
// - the map's size (shadow.mapSize; the depth texture is DEPTH_COMPONENT24, the unorm24 the bias was fitted
//   for: WebGLShadowMap.js DepthTexture(UnsignedIntType), WebGLTextures.js), nearest-texel lookups
//   (renderer.shadowMap.type = BasicShadowMap: NearestFilter, no comparison sampler), both faces of every
//   caster in the map (material.shadowSide = DoubleSide: getDepthMaterial), every mesh casting and receiving.
// - depth clamping in the light pass where the browser has EXT_depth_clamp (casters in front of the map's near
//   plane are pancaked onto it, which the solution's light_depth assumes): enabled around each mesh's shadow
//   draw (Object3D.onBeforeShadow / onAfterShadow), so the camera's own pass is untouched.
// - cascades: through three's CSM addon (ctx.CSM, examples/jsm/csm/): its lights take the maps, its shader selects
//   them by the solution's splits (below).
// dispose() restores every property it changed (renderer.shadowMap.enabled and type, the light's castShadow and
// shadow fields, the meshes' castShadow, receiveShadow, customDepthMaterial and shadow hooks, the materials'
// shadowSide). update() asks for the map to be redrawn (for a renderer.shadowMap.autoUpdate = false page).

const SOLUTION = @@SOLUTION@@;

export const solution = SOLUTION;

export default function apply(THREE, ctx) {
	const { renderer, scene, light } = ctx;
	const saved = [];
	const set = (obj, key, value) => {
		saved.push([obj, key, Object.prototype.hasOwnProperty.call(obj, key), obj[key]]);
		obj[key] = value;
	};
	const created = [];
	const dispose = () => {
		for (let i = saved.length - 1; i >= 0; i--) {
			const [obj, key, own, value] = saved[i];
			if (own) obj[key] = value; else delete obj[key];
		}
		saved.length = 0;
		for (const m of created) m.dispose();
		created.length = 0;
		if (light.shadow) light.shadow.needsUpdate = true;
	};
	if (!light || light.isDirectionalLight !== true) {
		throw new Error("shadowopt: ctx.light must be a THREE.DirectionalLight (this solution is for a directional light)");
	}
	if (SOLUTION.maps.length === 0) {  // shadow "none": no visible surface faces the light; it casts no shadow
		set(light, "castShadow", false);
		return { update() {}, dispose };
	}
	const maps = SOLUTION.maps;
	const maxSize = renderer.capabilities.maxTextureSize;
	const install = (shadow, map) => {  // one map into one LightShadow: matrices, bias, normal bias, size
		const cam = shadow.camera;
		const view = new THREE.Matrix4().fromArray(map.view_matrix);  // column-major, as Matrix4.fromArray reads
		const proj = new THREE.Matrix4().fromArray(map.projection_matrix);
		const texture = new THREE.Matrix4().fromArray(map.texture_matrix);
		const viewInverse = view.clone().invert();
		const projInverse = proj.clone().invert();
		const projView = proj.clone().multiply(view);
		if (map.resolution[0] > maxSize || map.resolution[1] > maxSize) {
			console.warn(`shadowopt: the map is ${map.resolution[0]}x${map.resolution[1]}, this renderer's largest texture ` +
				`is ${maxSize}: three.js will shrink it and the solution's texels no longer hold`);
		}
		set(shadow, "bias", -map.depth.constant);
		set(shadow, "normalBias", map.depth.normal_offset);
		set(shadow, "mapSize", new THREE.Vector2(map.resolution[0], map.resolution[1]));
		set(shadow, "updateMatrices", function () {
			cam.projectionMatrix.copy(proj);
			cam.projectionMatrixInverse.copy(projInverse);
			cam.matrixWorldInverse.copy(view);
			cam.matrixWorld.copy(viewInverse);
			shadow.matrix.copy(texture);
			shadow.getFrustum().setFromProjectionMatrix(projView, cam.coordinateSystem, false);
		});
		shadow.needsUpdate = true;
	};
	set(renderer.shadowMap, "enabled", true);
	set(renderer.shadowMap, "type", THREE.BasicShadowMap);
	const materials = new Set(ctx.materials || []);
	scene.traverse((o) => { if (o.isMesh) for (const m of [].concat(o.material)) if (m) materials.add(m); });

	let shadows, csm = null;
	if (maps.length === 1) {
		set(light, "castShadow", true);
		install(light.shadow, maps[0]);
		shadows = [light.shadow];
	} else {
		// Cascades through three's CSM addon (examples/jsm/csm/CSM.js, CSMShader.js): one DirectionalLight per map,
		// made by CSM; each light's shadow takes its map as above (CSM.update() only moves the lights, whose
		// shadow cameras no longer follow them). CSM's patched shader serves cascade i where the view depth over
		// (shadowFar - camera.near) lies in [breaks[i - 1], breaks[i]) (shadowFar = min(camera.far, maxFar)), with
		// fade off: the breaks are each blend band's midpoint, where evaluate switches maps, over that span, and
		// past the far plane for the last. The user's light is hidden (CSM's lights light the scene in its place,
		// with its colour and intensity); every material is set up for CSM.
		const CSM = ctx.CSM, camera = ctx.camera;
		if (!CSM || !camera) throw new Error(`shadowopt: this solution has ${maps.length} cascades: pass three's CSM addon ` +
			"class (three/addons/csm/CSM.js) as ctx.CSM and the camera as ctx.camera");
		const span = camera.far - camera.near;
		const breaks = maps.map((m, i) => i < maps.length - 1
			? (m.blend_band ? (m.blend_band[0] + m.blend_band[1]) / 2 : m.split[1]) / span
			: camera.far / span + 1);
		const chunks = ["lights_fragment_begin", "lights_pars_begin"].map((c) => [c, THREE.ShaderChunk[c]]);
		for (const [c, text] of chunks) set(THREE.ShaderChunk, c, text);  // CSM replaces them; dispose puts them back
		const d = SOLUTION.direction;
		csm = new CSM({ camera, parent: scene, cascades: maps.length, maxFar: camera.far, mode: "custom",
			customSplitsCallback: (n, near, far, target) => { for (const b of breaks) target.push(b); },
			shadowMapSize: maps[0].resolution[0], lightDirection: new THREE.Vector3(d[0], d[1], d[2]).normalize(),
			lightIntensity: light.intensity });
		csm.fade = false;
		csm.lights.forEach((l, i) => { l.color.copy(light.color); l.intensity = light.intensity; install(l.shadow, maps[i]); });
		set(light, "visible", false);
		for (const m of materials) {
			set(m, "onBeforeCompile", m.onBeforeCompile);
			set(m, "defines", { ...(m.defines || {}) });
			csm.setupMaterial(m);
			m.needsUpdate = true;
		}
		csm.update();
		shadows = csm.lights.map((l) => l.shadow);
	}

	for (const m of materials) set(m, "shadowSide", THREE.DoubleSide);

	const gl = renderer.getContext();
	const clamp = gl.getExtension("EXT_depth_clamp");
	const k = maps[0].depth.slope_scaled;  // one for every map (service/emit_three.py checks)
	const offsetMaterials = new Map();
	const offsetMaterial = (base) => {  // the mesh's own custom depth material with the offset, or a plain one
		if (!offsetMaterials.has(base)) {
			const m = base ? base.clone() : new THREE.MeshDepthMaterial();
			m.polygonOffset = true;
			m.polygonOffsetFactor = k;
			m.polygonOffsetUnits = 0;
			created.push(m);
			offsetMaterials.set(base, m);
		}
		return offsetMaterials.get(base);
	};
	scene.traverse((o) => {
		if (!o.isMesh) return;
		set(o, "castShadow", true);
		set(o, "receiveShadow", true);
		if (k > 0) set(o, "customDepthMaterial", offsetMaterial(o.customDepthMaterial));
		if (clamp) {
			const before = o.onBeforeShadow, after = o.onAfterShadow;
			set(o, "onBeforeShadow", function (...args) { gl.enable(clamp.DEPTH_CLAMP_EXT); return before.apply(this, args); });
			set(o, "onAfterShadow", function (...args) { gl.disable(clamp.DEPTH_CLAMP_EXT); return after.apply(this, args); });
		}
	});
	const disposeAll = () => {
		if (csm) {
			for (const l of csm.lights) l.shadow.dispose();
			csm.dispose();
			csm.remove();
		}
		dispose();
		for (const m of materials) m.needsUpdate = true;
	};
	return {
		update() { if (csm) csm.update(); for (const s of shadows) s.needsUpdate = true; },
		dispose: disposeAll,
		depthClamp: Boolean(clamp),
		csm,
	};
}
