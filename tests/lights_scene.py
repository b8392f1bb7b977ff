"""The demo scene with a spot and a point light added, for the tests of local lights (the inspector's browser
tests and the document's listings in OpenGL): a spot over the crate, pole and container (its -Z rotated 145
degrees about X: down and along +Z, where the camera looks; cone half-angle 50 degrees) and a bare sphere light
(a point light) among them."""
from __future__ import annotations

from pathlib import Path

from serverkit import DEMO

LIGHTS = '''
    def SphereLight "Spot" (
        prepend apiSchemas = ["ShapingAPI"]
    )
    {
        float inputs:intensity = 50
        float inputs:radius = 0.05
        float inputs:shaping:cone:angle = 50
        float3 xformOp:rotateXYZ = (-145, 0, 0)
        double3 xformOp:translate = (0, 6, 4)
        uniform token[] xformOpOrder = ["xformOp:translate", "xformOp:rotateXYZ"]
    }

    def SphereLight "Bulb"
    {
        float inputs:intensity = 50
        float inputs:radius = 0.05
        double3 xformOp:translate = (3, 5, 12)
        uniform token[] xformOpOrder = ["xformOp:translate"]
    }
'''


def write_lights_scene(folder: Path) -> Path:
    """The demo scene with LIGHTS inside its /World, written to folder/demo_lights.usda."""
    src = DEMO.read_text()
    end = src.rstrip().rfind("}")
    path = Path(folder) / "demo_lights.usda"
    path.write_text(src[:end] + LIGHTS + src[end:])
    return path
