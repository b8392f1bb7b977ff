"""Request and response schemas shared by the CLI, the REST API and the Python client.

Only pydantic here: the client installs without the rendering stack. The rig's field names are
fixed by the product (issue 2); unknown fields are refused so a typo names itself.
"""
from __future__ import annotations

from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

Finite = Annotated[float, Field(allow_inf_nan=False)]
Vec3 = tuple[Finite, Finite, Finite]
Resolution = tuple[Annotated[int, Field(gt=0, le=16384)], Annotated[int, Field(gt=0, le=16384)]]


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", populate_by_name=True)


class CameraSpec(_Strict):
    """A camera given explicitly (position + target or forward) or by its USD path in the scene."""

    usd_path: str | None = Field(None, description="a UsdGeom.Camera in the scene, e.g. /World/Camera")
    position: Vec3 | None = None
    target: Vec3 | None = Field(None, description="a point the camera looks at")
    forward: Vec3 | None = Field(None, description="the view direction (instead of target)")
    up: Vec3 = (0.0, 1.0, 0.0)
    fov_y_deg: Annotated[float, Field(gt=0, lt=180)] | None = Field(None, description="vertical field of view; default 60")
    near: Annotated[float, Field(gt=0, allow_inf_nan=False)] | None = None
    far: Annotated[float, Field(gt=0, allow_inf_nan=False)] | None = None
    resolution: Resolution = (1280, 720)

    @model_validator(mode="after")
    def _one_pose(self):
        if self.usd_path is None:
            if self.position is None:
                raise ValueError("give either usd_path or position with target or forward")
            if (self.target is None) == (self.forward is None):
                raise ValueError("give exactly one of target and forward")
        if self.near is not None and self.far is not None and not self.near < self.far:
            raise ValueError(f"near ({self.near}) must be less than far ({self.far})")
        return self


class LightSpec(_Strict):
    """`{"type": "directional", "direction"}`, `{"type": "spot", "position", "direction", "cone_deg"}`,
    `{"type": "point", "position"}`, or `{"usd_path": "/World/Sun"}`. `direction` is where light travels."""

    type: Literal["directional", "spot", "point"] | None = None
    usd_path: str | None = None
    direction: Vec3 | None = None
    position: Vec3 | None = None
    cone_deg: Annotated[float, Field(gt=0, le=180)] | None = Field(None, description="spot half-angle")

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


class ShadowSpec(_Strict):
    resolution: Resolution | None = Field(None, description="texels per map (width, height)")
    texel_budget: Annotated[int, Field(gt=0)] | None = Field(None, description="total texels per light")
    cascades: Annotated[int, Field(ge=1, le=16)] | Literal["auto"] = 1
    max_cascades: Annotated[int, Field(ge=1, le=16)] = 4
    target_p95_m: Annotated[float, Field(gt=0)] | None = None
    splits: Literal["practical", "log", "uniform", "optimized"] = "practical"
    lambda_: Annotated[float, Field(ge=0, le=1)] = Field(0.5, alias="lambda")

    @model_validator(mode="after")
    def _budget(self):
        if self.resolution is not None and self.texel_budget is not None:
            raise ValueError("give resolution or texel_budget, not both")
        if self.resolution is None and self.texel_budget is None:
            self.resolution = (2048, 2048)
        return self


class OutputSpec(_Strict):
    convention: Literal["opengl", "d3d", "vulkan"] = "opengl"
    layout: Literal["row_major", "column_major"] = "column_major"
    frame: Literal["world", "stage"] = "world"
    allow_log_warp: bool = False


class Rig(_Strict):
    """Camera, lights and shadow budget. Positions are in the world frame (right-handed, +Y up,
    meters) unless `frame` is "stage": then in the stage's own units and up axis."""

    camera: CameraSpec
    lights: list[LightSpec] = Field(min_length=1, max_length=16)
    shadow: ShadowSpec = ShadowSpec()
    output: OutputSpec = OutputSpec()
    frame: Literal["world", "stage"] = "world"
    coarse_long_side: Annotated[int, Field(ge=16, le=1024)] = Field(180, description="coarse buffer's long side, px")


def format_validation_error(err) -> str:
    """One line per problem: `field.path: reason` (pydantic ValidationError -> text)."""
    lines = []
    for e in err.errors():
        loc = ".".join(str(p) for p in e.get("loc", ())) or "(root)"
        msg = e.get("msg", "invalid").removeprefix("Value error, ")
        lines.append(f"{loc}: {msg}")
    return "; ".join(lines)


