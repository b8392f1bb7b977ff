// The Babylon.js page (service/bench/babylon_page.py: shadowopt bench engines, tests/test_babylon_module.py): the scene's triangles (already in Babylon's left-handed
// frame), the rig's camera and sun, the emitted module imported as it is, then three renders read back:
// - lit, twice: a white StandardMaterial (no ambient, no specular, both faces) lit by the sun alone, with the
//   module's shadows and with light.shadowEnabled = false; FILTER_NONE makes the shadow term 0 or 1, so "shadowed"
//   is a ratio under one half;
// - depth: the same triangles' view depth (z in Babylon's left-handed view space, the camera looks down +Z) in a
//   float render target, 0 where nothing is hit, so the test compares only pixels where Babylon's rasterizer and the
//   ray caster see the same surface.
import { Engine } from "@babylonjs/core/Engines/engine.js";
import { Scene } from "@babylonjs/core/scene.js";
import { FreeCamera } from "@babylonjs/core/Cameras/freeCamera.js";
import { Mesh } from "@babylonjs/core/Meshes/mesh.js";
import { VertexData } from "@babylonjs/core/Meshes/mesh.vertexData.js";
import { StandardMaterial } from "@babylonjs/core/Materials/standardMaterial.js";
import { ShaderMaterial } from "@babylonjs/core/Materials/shaderMaterial.js";
import { RenderTargetTexture } from "@babylonjs/core/Materials/Textures/renderTargetTexture.js";
import { DirectionalLight } from "@babylonjs/core/Lights/directionalLight.js";
import { ShadowGenerator } from "@babylonjs/core/Lights/Shadows/shadowGenerator.js";
import "@babylonjs/core/Lights/Shadows/shadowGeneratorSceneComponent.js";
import { Matrix, Vector3 } from "@babylonjs/core/Maths/math.vector.js";
import { Color3, Color4 } from "@babylonjs/core/Maths/math.color.js";
import { Constants } from "@babylonjs/core/Engines/constants.js";
import { CascadedShadowGenerator } from "@babylonjs/core/Lights/Shadows/cascadedShadowGenerator.js";
import { MeshBuilder } from "@babylonjs/core/Meshes/meshBuilder.js";

const BABYLON = { Matrix, Vector3, ShadowGenerator, CascadedShadowGenerator, Constants };  // what the modules use

function babylonCamera(scene, cam) {  // the rig's camera, already in Babylon's frame
	const camera = new FreeCamera("camera", new Vector3(...cam.position), scene);
	camera.upVector = new Vector3(...cam.up);
	camera.setTarget(new Vector3(cam.position[0] + cam.forward[0], cam.position[1] + cam.forward[1], cam.position[2] + cam.forward[2]));
	camera.fovMode = FreeCamera.FOVMODE_VERTICAL_FIXED;
	camera.fov = cam.fov_y_deg * Math.PI / 180;
	camera.minZ = cam.near; camera.maxZ = cam.far;
	scene.activeCamera = camera;
	return camera;
}

// tests/test_engine_fit_babylon.py: Babylon's own CascadedShadowGenerator for each of p.runs' settings, with one box
// caster (its render list's bounding box tightens each cascade's depth range): its cascades' transform matrices
// (getCascadeTransformMatrix, Matrix.m order) after one render, and what numCascades and shadowMaxZ hold.
export async function fitCascades(p) {
	const [W, H] = p.screen;
	const canvas = document.getElementById("c");
	canvas.width = W; canvas.height = H;
	const engine = new Engine(canvas, false, {}, false);
	engine.setHardwareScalingLevel(1);
	engine.setSize(W, H);
	const results = [];
	for (const s of p.runs) {
		const scene = new Scene(engine);
		const camera = babylonCamera(scene, p.camera);
		const d = p.sun_direction;
		const light = new DirectionalLight("sun", new Vector3(d[0], d[1], d[2]), scene);
		const [lo, hi] = p.casters_box;
		const box = MeshBuilder.CreateBox("casters", { width: hi[0] - lo[0], height: hi[1] - lo[1], depth: hi[2] - lo[2] }, scene);
		box.position = new Vector3((lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, (lo[2] + hi[2]) / 2);
		const csm = new CascadedShadowGenerator(s.mapSize, light, undefined, camera);
		csm.numCascades = s.numCascades; csm.lambda = s.lambda; csm.shadowMaxZ = s.shadowMaxZ;
		csm.stabilizeCascades = s.stabilizeCascades; csm.depthClamp = s.depthClamp; csm.bias = s.bias;
		csm.filter = s.filter === "NONE" ? ShadowGenerator.FILTER_NONE : ShadowGenerator.FILTER_PCF;
		csm.addShadowCaster(box);
		await scene.whenReadyAsync();
		scene.render();
		const out = { numCascades: csm.numCascades, shadowMaxZ: csm.shadowMaxZ, transforms: [] };
		for (let i = 0; i < csm.numCascades; i++) out.transforms.push(Array.from(csm.getCascadeTransformMatrix(i).m));
		results.push(out);
		scene.dispose();
	}
	engine.dispose();
	return { runs: results };
}

export async function render(p) {
	const [W, H] = p.screen;
	const canvas = document.getElementById("c");
	canvas.width = W; canvas.height = H;
	canvas.style.width = `${W}px`; canvas.style.height = `${H}px`;
	const engine = new Engine(canvas, false, { preserveDrawingBuffer: true, stencil: false }, false);
	engine.setHardwareScalingLevel(1);
	engine.setSize(W, H);
	const scene = new Scene(engine);
	scene.clearColor = new Color4(0, 0, 0, 0);
	scene.ambientColor = new Color3(0, 0, 0);

	const data = new Float32Array(await (await fetch(p.geometry)).arrayBuffer());  // x y z nx ny nz per vertex
	const n = data.length / 6;
	const positions = new Float32Array(3 * n), normals = new Float32Array(3 * n), indices = new Uint32Array(n);
	for (let i = 0; i < n; i++) {
		for (let c = 0; c < 3; c++) { positions[3 * i + c] = data[6 * i + c]; normals[3 * i + c] = data[6 * i + 3 + c]; }
		indices[i] = i;
	}
	const mesh = new Mesh("scene", scene);
	const vd = new VertexData();
	vd.positions = positions; vd.normals = normals; vd.indices = indices;
	vd.applyToMesh(mesh);
	mesh.alwaysSelectAsActiveMesh = true;
	const material = new StandardMaterial("white", scene);
	material.diffuseColor = new Color3(1, 1, 1);
	material.specularColor = new Color3(0, 0, 0);
	material.backFaceCulling = false;
	mesh.material = material;

	const d = p.sun_direction;  // Babylon's frame
	const light = new DirectionalLight("sun", new Vector3(d[0], d[1], d[2]), scene);
	light.position = new Vector3(-d[0] * 100, -d[1] * 100, -d[2] * 100);
	light.intensity = 1;
	light.specular = new Color3(0, 0, 0);

	const camera = babylonCamera(scene, p.camera);

	const mod = await import(p.module);
	const handle = mod.default(BABYLON, { engine, scene, camera, light, meshes: [mesh] });
	if (handle.update) handle.update();

	const frame = async () => {
		await scene.whenReadyAsync();
		for (let i = 0; i < 3; i++) scene.render();
		return new Uint8Array((await engine.readPixels(0, 0, W, H)).buffer);
	};
	const lit = await frame();
	light.shadowEnabled = false;
	const unshadowed = await frame();
	light.shadowEnabled = true;
	const shadowed = new Uint8Array(W * H);  // 255: Babylon shadows the pixel
	for (let i = 0; i < W * H; i++) shadowed[i] = lit[4 * i] < 0.5 * unshadowed[4 * i] ? 255 : 0;

	const depthMaterial = new ShaderMaterial("viewDepth", scene, {
		vertexSource: "precision highp float; attribute vec3 position; uniform mat4 world; uniform mat4 view; uniform mat4 projection; varying float vDepth; void main() { vec4 v = view * world * vec4(position, 1.0); vDepth = v.z; gl_Position = projection * v; }",
		fragmentSource: "precision highp float; varying float vDepth; void main() { gl_FragColor = vec4(vDepth, 1.0, 0.0, 1.0); }",
	}, { attributes: ["position"], uniforms: ["world", "view", "projection"] });
	depthMaterial.backFaceCulling = false;
	const target = new RenderTargetTexture("depth", { width: W, height: H }, scene, false, true, Constants.TEXTURETYPE_FLOAT);
	target.renderList = [mesh];
	target.activeCamera = camera;
	target.clearColor = new Color4(0, 0, 0, 0);
	target.setMaterialForRendering(mesh, depthMaterial);
	await new Promise((resolve) => { const tick = () => (depthMaterial.isReady(mesh) ? resolve() : setTimeout(tick, 10)); tick(); });
	target.render();
	const depth = new Float32Array((await target.readPixels()).buffer);

	const sg = handle.shadowGenerator;
	const installed = { filter: sg.filter, bias: sg.bias, normalBias: sg.normalBias, mapSize: sg.getShadowMap().getSize().width,
		builder: typeof light.customProjectionMatrixBuilder === "function", receive: mesh.receiveShadows,
		depthClamp: Boolean(handle.depthClamp), halfFloat: Boolean(handle.halfFloat),
		transform: sg.getTransformMatrix ? Array.from(sg.getTransformMatrix().m) : null };
	if (handle.dispose) handle.dispose();
	const restored = { builder: light.customProjectionMatrixBuilder === undefined || light.customProjectionMatrixBuilder === null,
		receive: mesh.receiveShadows, generator: Boolean(light.getShadowGenerator()) };
	const z = new Float32Array(W * H);
	for (let i = 0; i < W * H; i++) z[i] = depth[4 * i + 1] > 0.5 ? depth[4 * i] : 0;
	const b64 = (a) => { let s = ""; const u = new Uint8Array(a.buffer); for (let i = 0; i < u.length; i += 0x8000) s += String.fromCharCode(...u.subarray(i, i + 0x8000)); return btoa(s); };
	engine.dispose();
	return { alpha: b64(shadowed), depth: b64(z), installed, restored };
}
