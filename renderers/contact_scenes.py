"""Scenes built around contacts, where the depth bias decides what an engine shows (`shadowopt bench
engine-truth`): objects resting on a floor, a figure close up, a room whose walls meet a ceiling, thin slats,
shelves with boxes. Deterministic usd-core stages like renderers.corpus's (the same MeshAccumulator and cache
rules), written to out/contact/ (SHADOWOPT_CONTACT_DIR overrides it). Never tuned on: the bench reports them.

Regenerate by hand: .venv/bin/python -m shadowopt.renderers.contact_scenes [DIR]
"""
from __future__ import annotations

from pathlib import Path

from .corpus import MeshAccumulator, build_text, ensure_file, new_stage, out_folder, write_all

CONTACT_VERSION = 1


def _stage(doc: str):
    return new_stage(f"shadowopt contact scenes v{CONTACT_VERSION}: {doc} (shadowopt.renderers.contact_scenes)")


def resting_objects(stage) -> None:
    """Boxes, a cylinder and a low plate resting exactly on a 6 m floor (zero gap at every contact)."""
    acc = MeshAccumulator()
    acc.box_between((-3.0, -0.1, -3.0), (3.0, 0.0, 3.0))
    acc.box((0.0, 0.25, 0.0), (0.5, 0.5, 0.5), yaw_deg=15)
    acc.box((-1.1, 0.15, 0.6), (0.8, 0.3, 0.4), yaw_deg=-30)
    acc.prism((1.0, 0.0, -0.5), 0.25, 0.9, segments=24)
    acc.box((0.6, 0.01, 1.0), (0.9, 0.02, 0.6))  # a plate 2 cm thick
    acc.box((-0.6, 0.6, -1.0), (0.3, 1.2, 0.3), yaw_deg=40)
    acc.define(stage, "/World/Objects")


def figure_closeup(stage) -> None:
    """A 0.3 m figure (stacked blocks, arms, a head) standing on a base, for a camera 0.8 m away."""
    acc = MeshAccumulator()
    acc.box_between((-0.4, -0.02, -0.4), (0.4, 0.0, 0.4))
    acc.box((0.0, 0.005, 0.0), (0.16, 0.01, 0.12))  # base plate on the ground
    acc.box((-0.03, 0.06, 0.0), (0.035, 0.1, 0.04))  # legs
    acc.box((0.03, 0.06, 0.0), (0.035, 0.1, 0.04))
    acc.box((0.0, 0.16, 0.0), (0.1, 0.1, 0.05))  # torso on the legs
    acc.box((-0.065, 0.15, 0.0), (0.025, 0.09, 0.025), yaw_deg=10)  # arms touching the torso
    acc.box((0.065, 0.15, 0.0), (0.025, 0.09, 0.025), yaw_deg=-10)
    acc.prism((0.0, 0.21, 0.0), 0.03, 0.05, segments=20)  # head on the torso
    acc.define(stage, "/World/Figure")


def room_corners(stage) -> None:
    """A 5 x 4 x 2.6 m room: walls meeting the floor and a ceiling, a window and a roof light letting the sun in."""
    acc = MeshAccumulator()
    acc.box_between((-2.5, -0.1, -2.0), (2.5, 0.0, 2.0))  # floor
    acc.box_between((-2.5, 2.6, -2.0), (0.5, 2.7, 2.0))  # ceiling, a roof light from x 0.5 to 1.5
    acc.box_between((1.5, 2.6, -2.0), (2.5, 2.7, 2.0))
    acc.box_between((-2.6, 0.0, -2.0), (-2.5, 2.6, 2.0))  # west wall
    acc.box_between((2.5, 0.0, -2.0), (2.6, 2.6, 2.0))  # east wall
    acc.box_between((-2.6, 0.0, -2.1), (2.6, 2.6, -2.0))  # north wall
    acc.box_between((-2.6, 0.0, 2.0), (-0.5, 2.6, 2.1))  # south wall with a window from x -0.5 to 1.0
    acc.box_between((1.0, 0.0, 2.0), (2.6, 2.6, 2.1))
    acc.box_between((-0.5, 0.0, 2.0), (1.0, 0.9, 2.1))
    acc.box_between((-0.5, 2.1, 2.0), (1.0, 2.6, 2.1))
    acc.box((-1.5, 0.4, -1.4), (1.2, 0.8, 0.6))  # a cabinet against the north wall
    acc.box((0.8, 0.375, 0.0), (1.0, 0.75, 0.7), yaw_deg=5)  # a table block
    acc.define(stage, "/World/Room")


def slats(stage) -> None:
    """A fence of 3 cm slats 2 cm apart and a ladder leaning on a wall, on a ground plane."""
    acc = MeshAccumulator()
    acc.box_between((-6.0, -0.1, -6.0), (6.0, 0.0, 6.0))
    for k in range(40):
        x = -2.0 + k * 0.05
        acc.box_between((x, 0.0, 0.0), (x + 0.03, 1.2, 0.02))
    acc.box_between((-2.0, 0.9, -0.05), (0.0, 0.96, 0.0))  # a rail touching the slats
    acc.box_between((2.0, 0.0, -1.5), (2.2, 3.0, 1.5))  # a wall
    for k in range(8):  # ladder rungs between two rails, leaning on the wall
        y = 0.3 + 0.3 * k
        x = 2.0 - 0.8 * (1 - y / 2.7)
        acc.box_between((x - 0.02, y, -0.25), (x + 0.02, y + 0.03, 0.25))
    acc.box((1.6, 1.35, -0.27), (0.04, 2.8, 0.04), yaw_deg=0)
    acc.box((1.6, 1.35, 0.27), (0.04, 2.8, 0.04), yaw_deg=0)
    acc.define(stage, "/World/Slats")


def shelves(stage) -> None:
    """A shelving unit of four boards with boxes standing on them, against a wall."""
    acc = MeshAccumulator()
    acc.box_between((-3.0, -0.1, -3.0), (3.0, 0.0, 3.0))
    acc.box_between((-1.6, 0.0, -0.55), (1.6, 2.2, -0.5))  # back wall
    acc.box_between((-1.2, 0.0, -0.5), (-1.17, 1.8, 0.0))  # sides
    acc.box_between((1.17, 0.0, -0.5), (1.2, 1.8, 0.0))
    for k, y in enumerate((0.05, 0.5, 0.95, 1.4)):
        acc.box_between((-1.17, y, -0.5), (1.17, y + 0.025, 0.0))
        for b in range(5):
            w = 0.12 + 0.05 * ((b + k) % 3)
            h = 0.1 + 0.08 * ((2 * b + k) % 4)
            x = -1.0 + 0.45 * b
            acc.box((x, y + 0.025 + h / 2, -0.25), (w, h, 0.25), yaw_deg=((b * 13 + k * 7) % 20) - 10)
    acc.define(stage, "/World/Shelves")


BUILDERS = {"resting_objects": resting_objects, "figure_closeup": figure_closeup, "room_corners": room_corners,
            "slats": slats, "shelves": shelves}
# The rig camera of each (the benchmark sets the resolution and draws the suns).
CAMERAS = {
    "resting_objects": {"position": [3.2, 1.8, 3.6], "target": [0.0, 0.2, 0.0], "fov_y_deg": 50, "near": 0.05,
                        "far": 40.0},
    "figure_closeup": {"position": [0.45, 0.32, 0.62], "target": [0.0, 0.12, 0.0], "fov_y_deg": 40, "near": 0.01,
                       "far": 5.0},
    "room_corners": {"position": [-2.2, 1.6, 1.7], "target": [1.5, 1.8, -1.5], "fov_y_deg": 70, "near": 0.05,
                     "far": 20.0},
    "slats": {"position": [-0.5, 1.5, 3.5], "target": [0.5, 0.6, 0.0], "fov_y_deg": 55, "near": 0.05, "far": 40.0},
    "shelves": {"position": [0.3, 1.3, 2.2], "target": [0.0, 0.8, -0.3], "fov_y_deg": 55, "near": 0.05, "far": 20.0},
}


def default_dir() -> Path:
    return out_folder("SHADOWOPT_CONTACT_DIR", "contact")


def scene_text(builder: str) -> str:
    return build_text(BUILDERS, builder, _stage, "contact scene")


def ensure_scene(builder: str, folder: str | Path | None = None) -> Path:
    return ensure_file(scene_text, builder, folder, default_dir)


def main(argv=None) -> int:
    return write_all(BUILDERS, ensure_scene, default_dir, argv)


if __name__ == "__main__":
    raise SystemExit(main())
