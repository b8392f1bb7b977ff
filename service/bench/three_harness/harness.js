// The test's three.js page (tests/test_three_module.py): the scene's triangles, the rig's camera and sun, the
// emitted module imported as it is, then two renders into render targets read back:
// - shadow, one map: a ShadowMaterial (opaque, both sides) whose alpha is exactly 1 - three's shadow term
//   (ShaderLib/shadow.glsl.js: opacity * (1.0 - getShadowMask())), so alpha > 0.5 is "shadowed" with no
//   lighting model or threshold on shading in between;
// - shadow, cascades: ShadowMaterial's getShadowMask multiplies every light's term, but CSM selects the cascade in
//   the lighting code (CSMShader.js lights_fragment_begin), so a white MeshLambertMaterial (no ambient light) is
//   drawn into a float target twice, receiving shadows and not, and "shadowed" is a ratio under one half;
// - depth: the same triangles' view depth (-z in the camera's view space) in a float target, 0 where nothing is hit,
//   so the test compares only pixels where three's rasterizer and the ray caster see the same surface.
export async function render(THREE, CSM, p) {
	const [W, H] = p.screen;
	const canvas = document.getElementById("c");
	const renderer = new THREE.WebGLRenderer({ canvas, antialias: false });
	renderer.setPixelRatio(1);
	renderer.setSize(W, H, false);
	const defaults = { type: renderer.shadowMap.type, enabled: renderer.shadowMap.enabled };

	const buf = await (await fetch(p.geometry)).arrayBuffer();
	const data = new Float32Array(buf);  // per vertex: x y z nx ny nz (flat normals, on the light's side)
	const n = data.length / 6;
	const pos = new Float32Array(3 * n), nrm = new Float32Array(3 * n);
	for (let i = 0; i < n; i++) for (let c = 0; c < 3; c++) { pos[3 * i + c] = data[6 * i + c]; nrm[3 * i + c] = data[6 * i + 3 + c]; }
	const geometry = new THREE.BufferGeometry();
	geometry.setAttribute("position", new THREE.BufferAttribute(pos, 3));
	geometry.setAttribute("normal", new THREE.BufferAttribute(nrm, 3));
	const lambert = p.classify === "lambert";
	const material = lambert ? new THREE.MeshLambertMaterial({ color: 0xffffff, side: THREE.DoubleSide })
		: new THREE.ShadowMaterial({ color: 0x000000, opacity: 1, transparent: false, side: THREE.DoubleSide });
	const mesh = new THREE.Mesh(geometry, material);
	mesh.frustumCulled = false;
	const scene = new THREE.Scene();
	scene.add(mesh);

	const light = new THREE.DirectionalLight(0xffffff, 1);  // pointed along the rig's sun
	const d = p.sun_direction;
	light.target.position.set(0, 0, 0);
	light.position.set(-d[0] * 100, -d[1] * 100, -d[2] * 100);
	scene.add(light, light.target);
	scene.updateMatrixWorld(true);

	const cam = p.camera;
	const camera = new THREE.PerspectiveCamera(cam.fov_y_deg, W / H, cam.near, cam.far);
	camera.position.fromArray(cam.position);
	camera.up.fromArray(cam.up);
	camera.lookAt(cam.position[0] + cam.forward[0], cam.position[1] + cam.forward[1], cam.position[2] + cam.forward[2]);
	camera.updateMatrixWorld(true);

	const mod = await import(p.module);
	const handle = mod.default(THREE, { renderer, scene, camera, light, materials: [material], CSM });
	if (handle.update) handle.update();

	renderer.setClearColor(0x000000, 0);
	const shadowed = new Uint8Array(W * H);  // 255: three shadows the pixel
	if (lambert) {
		const pass = (receive) => {
			mesh.receiveShadow = receive;
			const target = new THREE.WebGLRenderTarget(W, H, { type: THREE.FloatType });
			renderer.setRenderTarget(target);
			renderer.render(scene, camera);
			const out = new Float32Array(4 * W * H);
			renderer.readRenderTargetPixels(target, 0, 0, W, H, out);
			target.dispose();
			return out;
		};
		const lit = pass(true), unshadowed = pass(false);
		mesh.receiveShadow = true;
		for (let i = 0; i < W * H; i++) shadowed[i] = lit[4 * i] < 0.5 * unshadowed[4 * i] ? 255 : 0;
	} else {
		const shadowTarget = new THREE.WebGLRenderTarget(W, H, { type: THREE.UnsignedByteType });
		renderer.setRenderTarget(shadowTarget);
		renderer.render(scene, camera);
		const rgba = new Uint8Array(4 * W * H);
		renderer.readRenderTargetPixels(shadowTarget, 0, 0, W, H, rgba);
		for (let i = 0; i < W * H; i++) shadowed[i] = rgba[4 * i + 3];
	}

	const depthTarget = new THREE.WebGLRenderTarget(W, H, { type: THREE.FloatType });
	scene.overrideMaterial = new THREE.ShaderMaterial({
		side: THREE.DoubleSide,
		vertexShader: "varying float vDepth; void main() { vec4 mv = modelViewMatrix * vec4(position, 1.0); vDepth = -mv.z; gl_Position = projectionMatrix * mv; }",
		fragmentShader: "varying float vDepth; void main() { gl_FragColor = vec4(vDepth, 1.0, 0.0, 1.0); }",
	});
	renderer.setRenderTarget(depthTarget);
	renderer.render(scene, camera);
	const depth = new Float32Array(4 * W * H);
	renderer.readRenderTargetPixels(depthTarget, 0, 0, W, H, depth);
	renderer.setRenderTarget(null);
	scene.overrideMaterial = null;

	const shadows = handle.csm ? handle.csm.lights.map((l) => l.shadow) : [light.shadow];
	const installed = { type: renderer.shadowMap.type, bias: shadows.map((s) => s.bias),
		normalBias: shadows.map((s) => s.normalBias), shadowSide: material.shadowSide,
		shadowMapSize: shadows.map((s) => s.map ? [s.map.width, s.map.height] : null), depthClamp: Boolean(handle.depthClamp),
		lightVisible: light.visible };
	if (handle.dispose) handle.dispose();
	const restored = { type: renderer.shadowMap.type, enabled: renderer.shadowMap.enabled, shadowSide: material.shadowSide,
		bias: light.shadow.bias, normalBias: light.shadow.normalBias, castShadow: mesh.castShadow,
		lightVisible: light.visible, lights: scene.children.filter((o) => o.isLight).length,
		defines: Object.keys(material.defines || {}).length, chunksRestored: !THREE.ShaderChunk.lights_fragment_begin.includes("CSM") };
	// rows bottom-up as WebGL reads them; one byte per pixel: the shadow alpha; one float per pixel: the depth
	const alpha = shadowed, z = new Float32Array(W * H);
	for (let i = 0; i < W * H; i++) z[i] = depth[4 * i + 1] > 0.5 ? depth[4 * i] : 0;
	const b64 = (a) => { let s = ""; const u = new Uint8Array(a.buffer); for (let i = 0; i < u.length; i += 0x8000) s += String.fromCharCode(...u.subarray(i, i + 0x8000)); return btoa(s); };
	renderer.dispose();
	return { alpha: b64(alpha), depth: b64(z), installed, restored, defaults };
}
