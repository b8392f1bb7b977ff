// The test's Filament page (tests/test_filament_module.py): the scene's triangles as a binary glTF loaded by
// Filament's own glTF loader (its built-in ubershader materials: no matc), the rig's camera, one DIRECTIONAL light
// along the rig's sun and no other light, the emitted module imported as it is, then three renders read back from
// the canvas (post-processing off, so the canvas holds the linear shading, no tone mapping, dithering or AA):
// - lit: shadows on; unshadowed: the same frame with the light's shadow casting off. "Shadowed" is lit below one
//   half of unshadowed: the light's visibility below one half through Filament's PCF, the only light being the sun;
// - ids: the same triangles, unlit, each with its index + 1 in its vertex colour, so the test compares only pixels
//   where Filament and the ray caster see the same surface.
function frames(renderer, swapChain, view, n) {
	return new Promise((resolve) => {
		let k = 0;
		const step = () => { renderer.render(swapChain, view); if (++k < n) requestAnimationFrame(step); else resolve(); };
		requestAnimationFrame(step);
	});
}

async function loadAsset(engine, loader, url) {
	const asset = loader.createAsset(new Uint8Array(await (await fetch(url)).arrayBuffer()));
	await new Promise((resolve) => asset.loadResources(resolve, null, null, 1));
	return asset;
}

export async function render(Filament, p) {
	const [W, H] = p.screen;
	const canvas = document.getElementById("c");
	canvas.width = W; canvas.height = H;
	const engine = Filament.Engine.create(canvas, { preserveDrawingBuffer: true });
	const scene = engine.createScene();
	const renderer = engine.createRenderer();
	const swapChain = engine.createSwapChain();
	const camera = engine.createCamera(Filament.EntityManager.get().create());
	const view = engine.createView();
	view.setCamera(camera);
	view.setScene(scene);
	view.setViewport([0, 0, W, H]);
	view.setPostProcessingEnabled(false);
	renderer.setClearOptions({ clearColor: [0, 0, 0, 1], clear: true });
	const cam = p.camera;
	camera.setProjectionFov(cam.fov_y_deg, W / H, cam.near, cam.far, Filament.Camera$Fov.VERTICAL);
	const at = cam.position.map((x, i) => x + cam.forward[i]);
	camera.lookAt(cam.position, at, cam.up);
	camera.setExposureDirect(1.0);

	const loader = engine.createAssetLoader();
	const lit = await loadAsset(engine, loader, p.geometry);
	const entities = lit.getRenderableEntities();
	scene.addEntities(lit.getEntities());
	const light = Filament.EntityManager.get().create();
	Filament.LightManager.Builder(Filament.LightManager$Type.DIRECTIONAL)
		.direction(p.sun_direction).intensity(3.0).color([1, 1, 1]).castShadows(false).build(engine, light);
	scene.addEntity(light);
	const lm = engine.getLightManager(), rm = engine.getRenderableManager();
	const li = lm.getInstance(light);
	const flags = () => ({ light: lm.isShadowCaster(li),
		cast: entities.filter((e) => rm.isShadowCaster(rm.getInstance(e))).length,
		receive: entities.filter((e) => rm.isShadowReceiver(rm.getInstance(e))).length, entities: entities.length });
	const before = flags();

	const mod = await import(p.module);
	const ctx = { engine, scene, view, camera, light, lightManager: lm, entities };
	let strict = null;
	try { mod.default(Filament, ctx); } catch (e) { strict = String(e.message || e); }
	const afterThrow = flags();
	const handle = mod.default(Filament, { ...ctx, acceptDefaults: true });
	const installed = flags();
	if (handle.update) handle.update();

	const shot = async () => { await frames(renderer, swapChain, view, 3); return canvas.toDataURL("image/png"); };
	const on = await shot();
	lm.setShadowCaster(li, false);
	const off = await shot();
	lm.setShadowCaster(li, true);
	handle.dispose();
	const restored = flags();

	scene.removeEntities(lit.getEntities());
	const ids = await loadAsset(engine, loader, p.ids);
	scene.addEntities(ids.getEntities());
	const idShot = await shot();
	return { on, off, ids: idShot, strict, applied: handle.applied, reason: handle.reason,
		flags: { before, afterThrow, installed, restored } };
}
