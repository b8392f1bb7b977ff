"""Request and response schemas shared by the CLI, the REST API and the Python client.

Only pydantic here: the client installs without the rendering stack. The rig's field names are
fixed by the product; unknown fields are refused so a typo names itself.
"""
from __future__ import annotations

from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator


Finite = Annotated[float, Field(allow_inf_nan=False)]
Vec3 = tuple[Finite, Finite, Finite]
# The bounds of a rig's numbers (service/rig_bounds.py states them for resolved rigs, USD cameras and lights
# included; tests/test_rig_bounds.py checks that the two agree): wide enough for every shipped and open-world rig
FOV_Y_DEG = (0.01, 179.0)
CONE_DEG = (0.01, 180.0)
NEAR_M = (1e-6, 1e8)
MAX_FAR = 1e9
MAX_FAR_OVER_NEAR = 1e7
MAX_COORDINATE = 1e9  # the distance from the scene's bounds is checked once the scene is known (max_rig_distance_m)
Coordinate = Annotated[float, Field(ge=-MAX_COORDINATE, le=MAX_COORDINATE, allow_inf_nan=False)]
Point3 = tuple[Coordinate, Coordinate, Coordinate]
Resolution = tuple[Annotated[int, Field(gt=0, le=16384)], Annotated[int, Field(gt=0, le=16384)]]


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", populate_by_name=True)


class CameraSpec(_Strict):
    """A camera given explicitly (position + target or forward) or by its USD path in the scene. With both a
    usd_path and a position (e.g. each pose of a camera path over a USD camera), the pose is the one given and
    the intrinsics (field of view, near, far, up) are the USD camera's unless given too."""

    usd_path: str | None = Field(None, description="a UsdGeom.Camera in the scene, e.g. /World/Camera")
    position: Point3 | None = None
    target: Point3 | None = Field(None, description="a point the camera looks at")
    forward: Vec3 | None = Field(None, description="the view direction (instead of target)")
    up: Vec3 | None = Field(None, description="default +Y (a USD camera: its own up)")
    fov_y_deg: Annotated[float, Field(ge=FOV_Y_DEG[0], le=FOV_Y_DEG[1], allow_inf_nan=False)] | None = Field(
        None, description="vertical field of view, degrees; default 60")
    near: Annotated[float, Field(ge=NEAR_M[0], le=NEAR_M[1], allow_inf_nan=False)] | None = None
    far: Annotated[float, Field(gt=0, le=MAX_FAR, allow_inf_nan=False)] | None = Field(
        None, description=f"at most {MAX_FAR_OVER_NEAR:g} x near")
    resolution: Resolution = (1280, 720)

    @model_validator(mode="after")
    def _one_pose(self):
        if self.usd_path is None and self.position is None:
            raise ValueError("give either usd_path or position with target or forward")
        if self.position is not None and (self.target is None) == (self.forward is None):
            raise ValueError("give exactly one of target and forward")
        if self.position is None and (self.target is not None or self.forward is not None):
            raise ValueError("target and forward need a position (a usd_path camera's own pose is used whole)")
        if self.near is not None and self.far is not None and not self.near < self.far:
            raise ValueError(f"near ({self.near}) must be less than far ({self.far})")
        if self.near is not None and self.far is not None and self.far / self.near > MAX_FAR_OVER_NEAR:
            raise ValueError(f"far / near = {self.far / self.near:.3g} (near {self.near:g}, far {self.far:g}) is over "
                             f"{MAX_FAR_OVER_NEAR:g}: no depth buffer resolves such a range; raise near or lower far")
        return self


class LightSpec(_Strict):
    """`{"type": "directional", "direction"}`, `{"type": "spot", "position", "direction", "cone_deg"}`,
    `{"type": "point", "position"}`, or `{"usd_path": "/World/Sun"}`. `direction` is where light travels."""

    type: Literal["directional", "spot", "point"] | None = None
    usd_path: str | None = None
    direction: Vec3 | None = None
    position: Point3 | None = None
    cone_deg: Annotated[float, Field(ge=CONE_DEG[0], le=CONE_DEG[1], allow_inf_nan=False)] | None = Field(
        None, description="spot half-angle, degrees")

    @model_validator(mode="after")
    def _complete(self):
        if self.usd_path is not None:
            return self
        need = {None: None, "directional": ("direction",), "spot": ("position", "direction", "cone_deg"),
                "point": ("position",)}[self.type]
        if need is None:
            raise ValueError("give a type (directional, spot, point) or a usd_path")
        missing = [f for f in need if getattr(self, f) is None]
        if missing:
            raise ValueError(f"a {self.type} light needs {', '.join(missing)}")
        return self


class DepthPin(_Strict):
    """Bias terms the user pins (the rest are fitted around them), in the units of a solution's depth block:
    constant and slope_clamp in stored depth ([0, 1] over the map's depth range), slope_scaled times the
    caster's stored-depth change per texel step, normal_offset in metres (the engine preset's unit with
    output.engine)."""

    mode: Literal["hardware", "linear"] | None = Field(None, description="the stored depth: window z (hardware) or "
                                                       "light-space distance (linear: a custom light pass)")
    constant: Annotated[float, Field(ge=0, le=1, allow_inf_nan=False)] | None = None
    slope_scaled: Annotated[float, Field(ge=0, le=100, allow_inf_nan=False)] | None = None
    slope_clamp: Annotated[float, Field(ge=0, le=1, allow_inf_nan=False)] | None = None
    normal_offset: Annotated[float, Field(ge=0, le=1e6, allow_inf_nan=False)] | None = None


class ShadowSpec(_Strict):
    bias: Literal["fitted", "rule"] = Field("fitted", description=(
        "fitted: each map's depth bias is chosen to minimize the wrong pixels the engine's depth test predicts "
        "(leaks at contacts and acne, with the terms the output engine applies); rule: a fixed rule (1.5 texels "
        "at the 95th percentile receiver, slope-scaled 1), what an engine user sets by hand"))
    depth: DepthPin | None = Field(None, description="bias terms to keep as given; the others are fitted around them")
    resolution: Resolution | None = Field(None, description="texels per map (width, height)")
    texel_budget: Annotated[int, Field(gt=0, le=16 * 16384 * 16384)] | None = Field(
        None, description="total texels per light (budget_scope light) or for the whole rig (budget_scope rig)")
    budget_scope: Literal["light", "rig"] = Field("light", description=(
        "rig: texel_budget is shared by all lights, split by need (Chong 2003's Lagrange allocation: each light's "
        "share grows with its predicted misclassified pixels; a light with no visible receiver gets none); "
        "the solution's texel_budget_split reports it"))
    cascades: Annotated[int, Field(ge=1, le=16)] | Literal["auto"] = 1
    max_cascades: Annotated[int, Field(ge=1, le=16)] = 4
    target_p95_m: Annotated[float, Field(gt=0, le=1e6, allow_inf_nan=False)] | None = Field(None, description=(
        "p95 texel footprint in pixels to meet: cascades auto takes the fewest cascades meeting it; when the "
        "maps meet it with fewer texels than allowed, a smaller resolution is returned (unless fixed_resolution)"))
    fixed_resolution: bool = Field(False, description="keep the given resolution or texel budget even when "
                                   "target_p95_m is met with fewer texels")
    point_light_maps: Literal["auto", "cube", "face_partition"] = Field("auto", description=(
        "point lights: auto keeps whichever of the cube map and Lloyd et al. 2007's face partitioning (maps only "
        "for faces with visible receivers, each fitted and warped) has the lower predicted objective; cube or "
        "face_partition forces one"))
    splits: Literal["practical", "log", "uniform", "optimized"] = "practical"
    snap_to_texels: bool = Field(False, description="unwarped directional maps: a texel grid fixed in the world "
                                 "(no shimmering while the camera moves without turning)")
    lambda_: Annotated[float, Field(ge=0, le=1)] = Field(0.5, alias="lambda")

    @model_validator(mode="after")
    def _budget(self):
        if self.resolution is not None and self.texel_budget is not None:
            raise ValueError("give resolution or texel_budget, not both")
        if self.budget_scope == "rig" and self.texel_budget is None:
            raise ValueError("budget_scope rig needs a texel_budget (the rig's total texels)")
        if self.resolution is None and self.texel_budget is None:
            self.resolution = (2048, 2048)
        return self


class OutputSpec(_Strict):
    """How the matrices are expressed. `engine` is a preset that sets convention, layout, reversed_z, the
    frame (handedness, up axis) and the length unit for that engine (docs/engines.md); giving it with a
    field it sets to a different value, or with frame "stage", is refused, naming both (frame "world",
    the default, is accepted with every preset)."""

    convention: Literal["opengl", "d3d", "vulkan"] = "opengl"
    layout: Literal["row_major", "column_major"] = "column_major"
    frame: Literal["world", "stage"] = "world"
    reversed_z: bool = Field(False, description="reversed depth: the light's near plane at depth 1 and its far "
                             "plane at 0 (clear to 0, compare greater), in the projection and texture matrices")
    engine: Literal["opengl", "d3d", "vulkan", "unity", "unreal", "godot", "three", "bevy", "filament", "babylon"] | None = Field(
        None, description="an engine preset: the matrices take points in that engine's world frame and units, "
        "and every length of the solution is in those units (docs/engines.md)")
    allow_log_warp: bool = False

    @model_validator(mode="after")
    def _preset(self):
        """Fill convention, layout and reversed_z from the engine preset (solvers.conventions.ENGINE_PRESETS);
        an explicit contradicting field is an error naming both. Without the server's stack (the bare
        client) the server checks."""
        if self.engine is None:
            return self
        try:
            from ..solvers.conventions import ENGINE_PRESETS, preset_conflicts  # lazy: absent in the bare client
        except ImportError:
            return self
        given = {k: getattr(self, k) for k in ("convention", "layout", "reversed_z", "frame")
                 if k in self.model_fields_set}
        bad = preset_conflicts(self.engine, given)
        if bad:
            raise ValueError("; ".join(bad))
        p = ENGINE_PRESETS[self.engine]
        self.convention, self.layout, self.reversed_z = p["convention"], p["layout"], p["reversed_z"]
        return self


class Rig(_Strict):
    """Camera, lights and shadow budget. Positions are in the world frame (right-handed, +Y up,
    meters) unless `frame` is "stage": then in the stage's own units and up axis."""

    camera: CameraSpec
    lights: list[LightSpec] = Field(min_length=1, max_length=16)
    shadow: ShadowSpec = ShadowSpec()
    output: OutputSpec = OutputSpec()
    frame: Literal["world", "stage"] = "world"
    coarse_long_side: Annotated[int, Field(ge=16, le=512)] = Field(
        180, description="coarse buffer's long side, px (the metric's samples: ~180 is the design point, 512 the cap)")

    @model_validator(mode="after")
    def _work(self):
        """The one bound on a rig's solve work (service.request_cost: lights x coarse pixels x maps, x6 for
        point lights, against MAX_SOLVE_WORK); every request and batch configuration with a rig passes here."""
        # lazy: the client's schemas load no service module at import (the bare client install)
        from ..service.request_cost import WorkLimit, check_solve_work

        try:
            check_solve_work(self)
        except WorkLimit as e:
            raise ValueError(e.message) from None
        return self


def validate_rig(raw: dict) -> dict:
    """A rig as the solver takes it: validated by `Rig` (defaults filled, aliases used); pydantic's
    ValidationError when it is not a valid rig (`format_validation_error` makes it one line). The CLI, the
    server's warm-up and the benchmarks validate rigs here."""
    return Rig.model_validate(raw).model_dump(by_alias=True)


def format_validation_error(err) -> str:
    """One line per problem: `field.path: reason` (pydantic ValidationError -> text)."""
    lines = []
    for e in err.errors():
        loc = ".".join(str(p) for p in e.get("loc", ())) or "(root)"
        msg = e.get("msg", "invalid").removeprefix("Value error, ")
        lines.append(f"{loc}: {msg}")
    return "; ".join(lines)




# --- REST API: requests and responses. Field names the clients rely on are fixed (additions only). ---

# service.methods.METHODS, written out: the bare client reads this module without the service package
# (tests/test_api.py checks the two lists are the same)
Method = Literal["uniform", "focused", "lispsm", "logpsm", "optimized", "stable_csm", "path"]
BatchState = Literal["queued", "running", "done", "failed", "cancelled"]
ObjectId = Annotated[str, Field(min_length=1, max_length=128, pattern=r"^[A-Za-z0-9_.-]+$")]


class _Open(BaseModel):
    """A response that may carry more fields than listed (they are additions, never renames)."""

    model_config = ConfigDict(extra="allow")


class ErrorBody(BaseModel):
    code: str = Field(description="machine-readable, e.g. scene_not_found, invalid_request, rate_limited")
    message: str = Field(description="what is wrong, naming the field")
    field: str | None = Field(None, description="the request field at fault, dotted (rig.camera.resolution)")


class ErrorResponse(BaseModel):
    """Every 4xx and 5xx answer of the REST API."""

    error: ErrorBody


class SceneInfo(_Open):
    """What the loader found in an uploaded scene (`LoadedScene.info()` plus its id)."""

    scene_id: str
    filename: str | None = None
    triangles: int
    vertices: int | None = None
    prims: int | None = None
    bounds: dict
    frame: dict
    cameras: list[dict]
    lights: list[dict]
    warnings: list[str]
    scene_hash: str | None = None
    created: bool | None = Field(None, description="false when the same file was already uploaded")


class Health(_Open):
    status: Literal["ok", "warming"]
    warm_s: float | None = Field(None, description="seconds the warm-up took")
    warm_errors: dict = Field(default_factory=dict)
    queue_length: int = Field(0, description="batch configurations waiting or running")
    version: str | None = None


class SceneList(BaseModel):
    scenes: list[dict]


class Deleted(BaseModel):
    deleted: bool


class _SceneRequest(_Strict):
    scene_id: ObjectId
    rig: Rig


class OptimizeRequest(_SceneRequest):
    """A scene id and rig; the answer is the solution schema of `shadowopt optimize`."""

    method: Method = "optimized"
    solver: Annotated[str, Field(max_length=64)] | None = Field(
        None, description="optimizer for method optimized (default nlopt:LN_BOBYQA)")
    time_budget_ms: Annotated[float, Field(gt=0, allow_inf_nan=False)] | None = Field(
        None, description="the optimizer's search time, ms, from the start of the solve over all lights and "
        "cascades (capped by the server); when it runs out the best maps so far are returned. It does not "
        "interrupt the coarse pass or the final fits: those are bounded by the rig's work limit")
    previous: dict | None = Field(None, description="the previous frame's solution (temporal stability)")
    hysteresis: Annotated[float, Field(gt=0, le=1)] = 0.8


class Warp(_Open):
    """The map's perspective warp: `kind` (none, lispsm, optimized, log...), its strength `eta` and the
    warp frustum's near distance `n` (light-view units; may be negative: the warp centre lies behind the
    receivers' near end), and LogPSM's `log` coefficients when a logarithmic warp is used."""

    kind: str = "none"
    eta: float | None = None
    n: float | None = None
    log: dict | None = None


Matrix16 = Annotated[list[float], Field(min_length=16, max_length=16)]


class ShadowMapSolution(_Open):
    """One shadow map (a cascade, or a cube face of a point light): matrices in the requested convention,
    layout and frame, and what they cover."""

    view_matrix: Matrix16 = Field(description="world (or stage, or the engine preset's frame) -> light view, 16 "
                                  "numbers in `layout` order")
    projection_matrix: Matrix16 = Field(description="light view -> clip space of the convention")
    texture_matrix: Matrix16 | None = Field(None, description="world (or stage, or the engine preset's frame) -> "
                                            "shadow-map texture coordinates and depth")
    resolution: tuple[int, int]
    split: tuple[float | None, float | None] = Field(description="the camera view-depth range this map serves, in "
                                                     "the solution's convention.length_unit (metres unless an engine "
                                                     "preset says otherwise; null: unbounded, e.g. a point light's faces)")
    light_depth: tuple[float | None, float | None] | None = Field(None, description="the least and greatest "
                                                                  "depth along the light view's -Z over the map's "
                                                                  "frustum (a warped map's frustum widens towards "
                                                                  "its far end)")
    warp: Warp = Warp()
    depth_bias: dict = Field(default_factory=dict)
    depth: dict | None = Field(None, description=(
        "what the engine stores and compares for this map: {mode: hardware | linear, reason, hardware: {constant, "
        "slope, normal_offset, slope_scaled, slope_clamp}, linear: {the same, near, far}}. hardware: the window z "
        "(z_ndc + 1) / 2 of projection * view a depth-only pass writes; linear: (-z_view - near) / (far - near) "
        "written by a custom light pass. The light pass stores clamp(D + min(slope_scaled * DZ, slope_clamp), 0, 1), "
        "DZ = max(|dD/dx|, |dD/dy|) per texel of the caster (hardware: glPolygonOffsetClamp(slope_scaled, 0, "
        "slope_clamp), D3D SlopeScaledDepthBias and DepthBiasClamp). Shadowed iff D(X') - (constant + slope * "
        "min(tan psi, 10)) > stored D, X' = X + normal_offset * N (metres along the receiver's light-facing "
        "normal); constant, slope and slope_clamp are in stored-depth units. constant_side caster (output.engine "
        "babylon): the constant is added to the caster's D before the depth format rounds it, and is 0 at the lookup"))
    blend_band: tuple[float, float] | None = Field(None, description="[start, end] camera depth where this "
                                                   "cascade blends into the next; null for the last or only map")
    face: str | None = None
    texel_snapped: bool = False
    texel_snap_note: str | None = Field(None, description="with shadow.snap_to_texels: why this map was not "
                                        "snapped (warped and perspective maps have no world-fixed texel grid)")
    predicted_error: dict | None = None


class LightSolution(_Open):
    """One light's maps and the predicted error over all of them."""

    type: str
    usd_path: str | None = None
    shadow: Literal["map", "none"] = Field("map", description=(
        "map: the light has visible receivers and its cascades are its maps; none: no visible receiver faces "
        "the light inside its cone, so it gets no map (cascades is empty) and casts no shadow: the engine "
        "renders none for it"))
    reason: str | None = Field(None, description="with shadow none: why, with the coarse buffer's counts")
    need: dict | None = Field(None, description="the light's receivers in the coarse buffer: seen_pixels, "
                              "in_cone_pixels, receiver_pixels (facing the light in its cone: lit or shadowed), "
                              "lit_pixels, shadowed_pixels, edge_points, edge_receivers")
    notes: list[str] | None = Field(None, description="what was dropped or changed and why (an empty cascade, "
                                    "a smaller resolution that meets target_p95_m)")
    cascades: list[ShadowMapSolution]
    predicted_error: dict


class _ReadAsDict:
    """Read access by key as on the JSON (`solution["lights"][0]`), for code written against plain dicts."""

    def __getitem__(self, key: str):
        data = self.model_dump(mode="json", by_alias=True)
        return data[key]

    def get(self, key: str, default=None):
        try:
            return self[key]
        except KeyError:
            return default

    def __contains__(self, key: str) -> bool:
        return key in self.model_dump(mode="json", by_alias=True)


class Solution(_ReadAsDict, _Open):
    """Light matrices, warp, cascades and predicted error per light (see docs/engine-integration.md).
    The Python client returns this model; `solution["lights"]` reads it as the JSON dict too."""

    schema_version: int
    method: str
    convention: dict
    lights: list[LightSolution]
    timings_ms: dict
    provenance: dict
    solver: dict | None = Field(None, description="the solver's report per light and cascade: which candidate won "
                                "and by how much; a candidate's score (`baselines`, `receiver_h`) is null where it is "
                                "infinite (the candidate leaves a receiver outside its map). Every number in a "
                                "response is finite (standard JSON): a non-finite value is written as null")
    resolved: dict | None = Field(None, description="what was solved for: the camera (position, forward, up, "
                                  "fov_y_deg, near, far, resolution), each light (type, direction and/or position, "
                                  "cone_deg), in the world frame (+Y up, metres), and the output convention")


class BatchResultLine(_ReadAsDict, _Open):
    """One line of `GET /v1/batches/{id}/results`: the configuration's `index` and either its solution's
    fields (method, lights, ...) or an `error` {code, message}."""

    index: int
    error: dict | None = None
    method: str | None = None
    lights: list[LightSolution] | None = None
    resolved: dict | None = Field(None, description="the camera and lights this configuration was solved for "
                                  "(as Solution.resolved)")

    @property
    def ok(self) -> bool:
        return self.error is None

    def solution(self) -> Solution:
        """The line as a `Solution` (ValueError for a failed configuration)."""
        if self.error is not None:
            raise ValueError(f"configuration {self.index} failed: {self.error.get('code')}: "
                             f"{self.error.get('message')}")
        data = self.model_dump(mode="json", by_alias=True)
        data.pop("index", None)
        data.pop("error", None)
        return Solution.model_validate(data)


DepthTest = Literal["solution", "hardware", "linear", "ideal"]
DEPTH_TEST_DESCRIPTION = (
    "the depth test emulated: solution (what an engine does with each map's `depth` block, in the mode it names), "
    "hardware (window z of the returned projection) or linear (light-space distance) for every map, or ideal (the "
    "idealized per-texel bias rule of `depth_bias`); the evaluation states it as `depth` and `depth_rule`")


class EvaluateRequest(_SceneRequest):
    """Measure a solution against exact ray-traced shadows on the scene."""

    solution: dict = Field(description="a solution returned by /v1/optimize for this scene and rig")
    screen: Resolution | None = Field(None, description="screen resolution (default: the rig camera's)")
    heatmap: bool = Field(False, description="also return a heatmap with its legend as PNG (base64)")
    heatmap_mode: Literal["m", "errors"] = Field(
        "m", description="m: the per-pixel m in the colour key of Lloyd et al. (2007); errors: wrongly shadowed and wrongly lit "
        "pixels in two colours over the exact shading, with their counts in the legend. The screen-sized "
        "picture is the PNG's top-left region, the legend the strip below it")
    grid_every: Annotated[int, Field(ge=1, le=4096)] | None = Field(None, description="texel grid overlay, texels")
    depth: DepthTest = Field("solution", description=DEPTH_TEST_DESCRIPTION)


class Evaluation(_Open):
    """Misclassified, boundary and outside pixels and `measured_error` in the pixels of `screen` (the
    evaluation's screen); `rig_resolution` is the rig camera's, the pixels of every `predicted_error`;
    `measured_error_rig_pixels` (when they differ) is the same measurement in the rig's pixels."""

    method: str | None = None
    timings_ms: dict
    heatmap_png_base64: list[str] | None = Field(None, description="one PNG per light, base64")


class CompareRequest(_SceneRequest):
    methods: list[Method] = Field(["uniform", "focused", "lispsm", "logpsm"], min_length=1, max_length=5)
    screen: Resolution | None = Field(None, description="where the ground truth is measured (default: the rig "
                                      "camera's resolution); every method is solved at the rig's resolution")
    depth: DepthTest = Field("solution", description=DEPTH_TEST_DESCRIPTION)

    @field_validator("methods")
    @classmethod
    def _work(cls, methods, info):
        """A compare runs one solve per method plus a warm-up solve: their work together is bounded (field
        `methods`; service.compare checks it again with the screen's aspect and the lights' real types, and the
        ground truth's work after the server's pixel and texel limits)."""
        # lazy: the client's schemas load no service module at import (the bare client install)
        from ..service.request_cost import WorkLimit, check_solve_work

        rig = info.data.get("rig")
        if rig is not None:
            try:
                check_solve_work(rig, solves=len(set(methods)) + 1)
            except WorkLimit as e:
                raise ValueError(f"{len(set(methods))} methods: {e.message}") from None
        return methods


class Comparison(_Open):
    """Per method: solution, predicted_error (the rig's pixels), evaluation (the screen's pixels, see
    Evaluation), setup_ms; `screen` and `rig_resolution` name the two."""

    methods: dict


class TuneRequest(_SceneRequest):
    """`POST /v1/tune`: an engine's own cascade settings for the rig's one directional light (docs/tune.md)."""

    engine: Annotated[str, Field(max_length=32)] = Field("three", description="the engine whose own cascades are "
                                                         "emulated and tuned (accepted: three)")
    settings: dict | None = Field(None, description="knobs to pin, under the engine's own names (e.g. {\"cascades\": "
                                  "4}); the search leaves them")
    poses: list[CameraSpec] | None = Field(None, max_length=16, description="more camera poses (as rig.camera): "
                                           "one setting serves them all, scored by the sum of their wrong pixels")
    camera_path: CameraPath | None = Field(None, description="more poses along a camera path (poses, or keyframes "
                                           "+ samples, over rig.camera)")
    sun_arc: SunArc | None = Field(None, description="score every camera under each sun of this arc (the rig's "
                                   "light replaced); at most 16 cameras x suns in all")
    time_budget_ms: Annotated[float, Field(gt=0, le=600_000, allow_inf_nan=False)] | None = Field(
        None, description="the search's time (default 1600 ms per pose less the coarse passes, capped by the "
        "server's time budget); past it no new candidate is scored (the answer's search.complete)")


class TunePrediction(_Open):
    """Wrong pixels the emulated engine's depth test predicts at the rig's screen (summed over the poses)."""

    misclassified_pixels: float
    wrongly_lit: float
    wrongly_shadowed: float


class TuneResult(_Open):
    """The tuned `settings` (the engine's own names) and their `predicted` wrong pixels; `defaults` (the engine's
    defaults with maxFar = the scene's reach and the solution's map size) with theirs; `emulated.cascades` (each
    cascade's near and far view depth where the engine selects it, and its light matrices); `snippet` (JS)."""

    engine: str
    engine_version: str
    settings: dict
    predicted: TunePrediction
    defaults: dict
    emulated: dict
    snippet: str
    timings_ms: dict


class AnalyzeRequest(_Strict):
    """Lloyd et al.'s scene-independent factors for one view frustum and light angle."""

    f_over_n: Annotated[float, Field(gt=1, le=1e9, allow_inf_nan=False)]
    theta_deg: Annotated[float, Field(gt=0, lt=90, allow_inf_nan=False)] = Field(description="half field of view")
    gamma_deg: Annotated[float, Field(ge=0, le=180, allow_inf_nan=False)] = Field(
        description="angle between light and view direction (90 = overhead)")
    method: Literal["uniform", "perspective", "log", "fp", "fp+p", "fp+log"] = Field(description=(
        "the warp of one map per z-partition (uniform, perspective, log), or face partitioning (Lloyd et al. 2007: "
        "fp, fp+p, fp+log: one map per face of the view frustum the light sees, partitions 1)"))
    partitions: Annotated[int, Field(ge=1, le=64)] = 1
    azimuth_deg: Annotated[float, Field(ge=-360, le=360, allow_inf_nan=False)] = 0.0


class Analysis(BaseModel):
    R_s: float
    R_t: float
    S: float
    maps: float | None = Field(None, description="face partitioning: the faces that get a map")


class BatchConfiguration(_Strict):
    rig: Rig


class ConfigurationError(ValueError):
    """A batch configuration that is not a valid rig: `field` (e.g. `configurations.3.rig.shadow.lambda`)
    and the reason, for the CLI (exit 2) and the API (422) alike."""

    def __init__(self, field: str, message: str):
        super().__init__(message)
        self.field, self.message = field, message


def validate_configurations(configs: list[dict]) -> list[dict]:
    """Each expanded configuration validated as {"rig": Rig}; the first bad one raises ConfigurationError
    with its path under `configurations.K`."""
    out = []
    for k, c in enumerate(configs):
        try:
            out.append(BatchConfiguration.model_validate(c).model_dump(by_alias=True))
        except ValidationError as e:
            errors = e.errors()
            first = ".".join(str(p) for p in ("configurations", k, *errors[0].get("loc", ())))
            text = "; ".join(f"configurations.{k}.{line}" for line in format_validation_error(e).split("; "))
            raise ConfigurationError(first, text) from e
    return out


class BatchCreated(_Open):
    batch_id: str
    state: BatchState
    total: int


class BatchStatus(_Open):
    batch_id: str
    scene_id: str
    state: BatchState
    done: int
    failed: int = 0
    total: int
    progress: float = Field(description="(done + failed) / total")
    errors: list[dict] = Field(default_factory=list)
    interpolation: dict | None = Field(None, description="how to interpolate between neighbouring "
                                       "configurations (when the batch is done)")


class CameraPath(_Strict):
    """Camera poses along a path: explicit `poses`, or `keyframes` (position and target or forward, optional
    up, fov_y_deg, near, far) interpolated linearly to `samples` poses. Each pose is laid over rig.camera."""

    poses: list[dict] | None = Field(None, min_length=1, max_length=100_000)
    keyframes: list[dict] | None = Field(None, min_length=2, max_length=10_000)
    samples: Annotated[int, Field(ge=1, le=10_000)] | None = None


AngleRange = Annotated[float, Field(allow_inf_nan=False)] | tuple[Finite, Finite]


class SunArc(_Strict):
    """Sun directions from (azimuth, elevation) `from` to `to` in `samples` steps (world frame, +Y up;
    azimuth 0 puts the sun toward +Z, 90 toward +X). Each angle is a number or [from, to] in degrees."""

    azimuth_deg: AngleRange = 0.0
    elevation_deg: AngleRange
    samples: Annotated[int, Field(ge=1, le=10_000)] = 1


class BatchRequest(_Strict):
    """A scene and its configurations: an explicit list of `{"rig": RIG}`, or the camera-path form: a base
    `rig` with a `camera_path` and/or light set (`light_directions` or `sun_arc`, replacing the rig's light
    `light_index`); index = camera_index * n_lights + light_index."""

    scene_id: ObjectId
    configurations: list[BatchConfiguration] | None = Field(None, min_length=1, max_length=100_000)
    rig: Rig | None = Field(None, description="the base rig of the camera-path form")
    camera_path: CameraPath | None = None
    light_directions: list[Vec3] | None = Field(None, min_length=1, max_length=10_000,
                                                description="directions light travels, world frame")
    sun_arc: SunArc | None = None
    light_index: Annotated[int, Field(ge=0, le=15)] | None = None
    method: Method = "optimized"
    solver: Annotated[str, Field(max_length=64)] | None = None
    time_budget_ms: Annotated[float, Field(gt=0, allow_inf_nan=False)] | None = None


class TimeRange(_Strict):
    """Time codes start, start + step, ... up to end (inclusive)."""

    start: Finite
    end: Finite
    step: Annotated[float, Field(gt=0, allow_inf_nan=False)] = 1.0


class PathRequest(_Strict):
    """A camera path solved frame by frame (a batch whose configurations are the frames in order): the base
    `rig` with a `camera_path` (poses, or keyframes + samples; optionally one light direction per frame from
    `light_directions` or `sun_arc`), or a USD camera animated by time samples (`usd_camera`, default
    rig.camera.usd_path, read at each code of `time`: pose, field of view, clipping range; the rig's USD lights
    read at the same codes). Results: `GET /v1/batches/{id}/results`, one line per frame with `frame` and `time`.
    `coherent`: frames are solved in order, each given the previous frame's solution (as `previous`)."""

    scene_id: ObjectId
    rig: Rig
    camera_path: CameraPath | None = None
    usd_camera: Annotated[str, Field(min_length=1, max_length=1024)] | None = None
    time: TimeRange | None = None
    light_directions: list[Vec3] | None = Field(None, min_length=1, max_length=10_000,
                                                description="one direction light travels per frame (or one), world frame")
    sun_arc: SunArc | None = None
    light_index: Annotated[int, Field(ge=0, le=15)] | None = None
    method: Method = "optimized"
    coherent: bool = Field(False, description="solve frames in order, each given the previous frame's solution")
    solver: Annotated[str, Field(max_length=64)] | None = None
    time_budget_ms: Annotated[float, Field(gt=0, allow_inf_nan=False)] | None = None


class PathFrame(BatchResultLine):
    """One line of a path job's results: a `BatchResultLine` with the frame index and its time code (None for
    a camera_path frame); a failed frame's line carries them too."""

    frame: int | None = None
    time: float | None = None
    scene_time: float | None = Field(None, description="the time code the stage's geometry was read at (moving "
                                     "geometry)")
    warnings: list[str] | None = Field(None, description="what the loader reported reading the stage at this "
                                       "frame's time code (e.g. a mesh skipped there for NaN points)")
