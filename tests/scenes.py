"""Small scene descriptions shared by the Python tests (plain functions, no fixtures)."""

from __future__ import annotations

import copy
from typing import Any

import numpy as np

#: Camera-to-world, column-major: no rotation (looking down -Z), placed at (0, 1.5, 6).
CAMERA_AT_0_1_6 = [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 1.5, 6, 1]


def build_scene(
    *,
    width: int = 64,
    height: int = 36,
    steps: int = 32,
    shadow_map_size: int = 64,
    occluder: bool = True,
) -> dict[str, Any]:
    """A ground-plane quad under a sun, optionally with a square occluder above it."""
    meshes: list[dict[str, Any]] = [
        {
            "name": "ground",
            "object_id": 0,
            "positions": [[-10, 0, -10], [10, 0, -10], [10, 0, 10], [-10, 0, 10]],
            "triangles": [[0, 1, 2], [0, 2, 3]],
        }
    ]
    if occluder:
        meshes.append(
            {
                "name": "occluder",
                "object_id": 7,
                "positions": [[-1, 3, -1], [1, 3, -1], [1, 3, 1], [-1, 3, 1]],
                "triangles": [[0, 1, 2], [0, 2, 3]],
            }
        )
    return {
        "version": 1,
        "camera": {
            "world_from_camera": list(CAMERA_AT_0_1_6),
            "projection": {"kind": "perspective", "focal_length": 35.0},
            "clip_start": 0.1,
            "clip_end": 100.0,
            "width": width,
            "height": height,
        },
        "sun": {"direction": [0.3, -1.0, -0.2], "strength": 3.0},
        "medium": {"extinction": 0.08, "anisotropy": 0.3},
        "meshes": meshes,
        "render": {
            "method": "reference",
            "shadow_map_size": shadow_map_size,
            "max_distance": 30.0,
            "steps": steps,
        },
    }


def move_occluder_off_the_float32_grid(scene: dict[str, Any]) -> None:
    """Puts `scene`'s occluder (from `build_scene`) where 100 km away no float32 holds its
    corners exactly, so that tests of scenes far from the origin see rounding."""
    occluder = scene["meshes"][1]
    occluder["positions"] = [
        [1.03717 * x, y + 0.01139, 1.03717 * z] for x, y, z in occluder["positions"]
    ]


def flatten(scene: dict[str, Any]) -> dict[str, Any]:
    """`render_arrays` keyword arguments equivalent to `scene` (its meshes in world space)."""
    positions, triangles, object_ids = [], [], []
    base = 0
    for mesh in scene["meshes"]:
        matrix = (
            np.asarray(mesh.get("world_from_object", np.eye(4).ravel()), dtype=np.float64)
            .reshape(4, 4)
            .T
        )  # column-major storage
        local = np.asarray(mesh["positions"], dtype=np.float64)
        world = local @ matrix[:3, :3].T + matrix[:3, 3]
        positions.append(world.astype(np.float32))
        triangles.append(np.asarray(mesh["triangles"], dtype=np.uint32) + base)
        object_ids.append(np.full(len(mesh["triangles"]), mesh["object_id"], dtype=np.uint32))
        base += len(local)
    return {
        "positions": np.concatenate(positions),
        "triangles": np.concatenate(triangles),
        "object_ids": np.concatenate(object_ids),
        "camera": copy.deepcopy(scene["camera"]),
        "sun": copy.deepcopy(scene["sun"]),
        "medium": copy.deepcopy(scene["medium"]),
        "settings": copy.deepcopy(scene.get("render", {})),
    }
