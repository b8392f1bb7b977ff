// A shadowopt solution as Filament settings, written by `shadowopt optimize --emit` (service/emit_filament.py).
// Import it as it is: `import apply from "./this.js"; const s = apply(Filament, ctx); ... s.dispose();`
// ctx = { engine, scene, view, camera, light, lightManager, entities, acceptDefaults }: `light` the Entity of a
// DIRECTIONAL or SUN light already pointed along the rig's sun; `lightManager` optional (engine.getLightManager());
// `entities` the renderable entities that cast and receive (e.g. a glTF asset's getRenderableEntities()), optional.
// Written for Filament.js @@FILAMENT_VERSION@@ (npm `filament`); Filament's files named below are google/filament's.
//
// Filament fits its light matrices itself, every frame (filament/src/ShadowMap.cpp, ShadowMapManager.cpp), and its
// JS API takes no matrix: this module installs the solution's SETTINGS, the light's LightManager ShadowOptions
// (filament/include/filament/LightManager.h), in Filament's names and units (service/emit_filament.py):
// - mapSize: the map's resolution; shadowCascades: the number of maps (1: the web build has no
//   cascadeSplitPositions, so a cascaded solution is refused when emitting);
// - polygonOffsetConstant: the solution's constant in DEPTH16 steps (constant x 65535) and polygonOffsetSlope: its
//   slope-scaled term; Filament applies both to the casters in its light pass, negated for its reversed Z
//   (ShadowMapManager.cpp: PolygonOffset{-polygonOffsetSlope, -polygonOffsetConstant}); constantBias 0;
// - normalBias: the solution's normal offset over half a texel (Filament moves the receiver by
//   0.5 normalBias texel sin(theta) along its normal);
// - stable, lispsm (honoured only by builds whose binding has it), shadowFar (0: the camera's far plane).
// It also turns shadow casting on for the light (LightManager.setShadowCaster) and casting and receiving on for
// ctx.entities (RenderableManager.setCastShadows / setReceiveShadows). dispose() puts those flags back and, when
// the options were applied, resets them to Filament.shadowOptions()'s defaults (the JS API cannot read them back).
// update() does nothing: Filament refits its maps every frame.
//
// Filament.js 1.53.4 cannot take ShadowOptions: LightManager.setShadowOptions throws embind's UnboundTypeError
// (its LightManager$ShadowOptions value object has a field whose C++ type is not bound: google/filament issue
// 10043, fixed by pull request 10116). Then apply() throws an Error saying so, after undoing what it set; with
// ctx.acceptDefaults it keeps Filament's default ShadowOptions instead and returns { applied: false, reason }.

const SOLUTION = @@SOLUTION@@;

export const solution = SOLUTION;

export default function apply(Filament, ctx) {
	const { engine, light } = ctx;
	const lm = ctx.lightManager || engine.getLightManager();
	const rm = engine.getRenderableManager();
	const li = lm.getInstance(light);
	if (!lm.isDirectional(li)) {
		throw new Error("shadowopt: ctx.light must be a DIRECTIONAL or SUN light (this solution is for a directional light)");
	}
	const undo = [];
	let applied = false;
	const dispose = () => {
		for (let i = undo.length - 1; i >= 0; i--) undo[i]();
		undo.length = 0;
		if (applied) lm.setShadowOptions(li, {});  // Filament.shadowOptions()'s defaults
		applied = false;
	};
	const caster = lm.isShadowCaster(li);
	undo.push(() => lm.setShadowCaster(li, caster));
	if (SOLUTION.shadowOptions === null) {  // shadow "none": no visible surface faces the light
		lm.setShadowCaster(li, false);
		return { update() {}, dispose, applied: true, reason: null };
	}
	lm.setShadowCaster(li, true);
	for (const e of ctx.entities || []) {
		const ri = rm.getInstance(e);
		const cast = rm.isShadowCaster(ri), receive = rm.isShadowReceiver(ri);
		rm.setCastShadows(ri, true);
		rm.setReceiveShadows(ri, true);
		undo.push(() => { const r = rm.getInstance(e); rm.setCastShadows(r, cast); rm.setReceiveShadows(r, receive); });
	}
	let reason = null;
	try {
		lm.setShadowOptions(li, SOLUTION.shadowOptions);
		applied = true;
	} catch (e) {
		if (!/unbound types/i.test(String(e && e.message || e))) { dispose(); throw e; }
		reason = `this Filament.js build cannot take ShadowOptions (${e.name}: ${e.message}; google/filament issue ` +
			"10043, fixed by pull request 10116): the light keeps Filament's defaults (mapSize 1024, one cascade, " +
			"constantBias 0.001, normalBias 1, polygon offset 0.5 / 2, LiSPSM on), not the solution's settings";
	}
	if (!applied && !ctx.acceptDefaults) {
		dispose();
		throw new Error(`shadowopt: ${reason}. Pass ctx.acceptDefaults = true to render with them anyway.`);
	}
	return { update() {}, dispose, applied, reason };
}
