"""A stage's up axis and units.

- Units: the stage's upAxis and metersPerUnit (USD's fallbacks: Y and 0.01) -> solvers.frames world.
"""
from __future__ import annotations

import math
import os

from pxr import UsdGeom


def stage_frame(stage, warnings, layer_name=None):
    layer = stage.GetRootLayer()
    up = "Y"
    if stage.HasAuthoredMetadata("upAxis"):
        up = str(stage.GetMetadata("upAxis"))
        if up not in ("Y", "Z"):
            warnings.append(f"upAxis {up!r} is not Y or Z: treated as Y")
            up = "Y"
    if stage.HasAuthoredMetadata("metersPerUnit"):
        mpu = float(stage.GetMetadata("metersPerUnit"))
        if not (math.isfinite(mpu) and mpu > 0):
            warnings.append(f"metersPerUnit {mpu!r} is not a positive number: USD's fallback 0.01 used")
            mpu = 0.01
    else:
        mpu = float(UsdGeom.GetStageMetersPerUnit(stage))
        warnings.append(f"metersPerUnit not authored: USD's fallback {mpu} (centimetres) used")
    # USD does not rescale layers authored in other units: say so when a composed layer differs.
    for other in stage.GetUsedLayers():
        shown = layer_name(other) if layer_name else (None if other.anonymous else os.path.basename(other.identifier))
        if other == layer or shown is None:
            continue
        try:
            info = other.pseudoRoot.GetInfo("metersPerUnit") if other.pseudoRoot.HasInfo("metersPerUnit") else None
        except Exception:  # noqa: BLE001 - metadata we cannot read is not worth failing for
            info = None
        if info is not None and not math.isclose(float(info), mpu, rel_tol=1e-9):
            warnings.append(f"layer {shown} is authored with metersPerUnit {float(info):g} but "
                            f"the stage uses {mpu:g}; USD does not rescale it, so it is read in the stage's units")
    return up, mpu
