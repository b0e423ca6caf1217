"""The physically based reference against Cycles: a fog box (Volume Scatter) lit by a sun
through a partial occluder, rendered by real Cycles and by crepuscular from the same
matrices. Cycles runs in a subprocess so that its state never leaks into other tests."""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap
from typing import Any

import numpy as np
import pytest

import crepuscular

WIDTH, HEIGHT = 96, 54
EXTINCTION = 0.35
ANISOTROPY = 0.3
SUN_STRENGTH = 3.0

CYCLES_SCRIPT = textwrap.dedent(
    """
    import json, sys
    import bpy
    from mathutils import Matrix

    spec = json.loads(sys.argv[1])
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene

    def place(obj, rows):
        obj.matrix_world = Matrix(rows)

    camera = bpy.data.objects.new("Camera", bpy.data.cameras.new("Camera"))
    scene.collection.objects.link(camera)
    camera.data.lens = 50.0
    camera.data.sensor_width = 36.0
    camera.data.sensor_fit = "AUTO"
    camera.data.clip_start = 0.1
    camera.data.clip_end = 100.0
    place(camera, spec["camera"])
    scene.camera = camera

    sun = bpy.data.objects.new("Sun", bpy.data.lights.new("Sun", type="SUN"))
    scene.collection.objects.link(sun)
    sun.data.energy = spec["strength"]
    sun.data.angle = 0.0
    place(sun, spec["sun"])

    bpy.ops.mesh.primitive_cube_add(size=2.0)
    fog = bpy.context.active_object
    place(fog, spec["fog"])
    material = bpy.data.materials.new("Fog")
    material.use_nodes = True
    nodes = material.node_tree.nodes
    nodes.remove(nodes["Principled BSDF"])
    scatter = nodes.new("ShaderNodeVolumeScatter")
    scatter.inputs["Color"].default_value = (1.0, 1.0, 1.0, 1.0)
    scatter.inputs["Density"].default_value = spec["extinction"]
    scatter.inputs["Anisotropy"].default_value = spec["anisotropy"]
    material.node_tree.links.new(
        scatter.outputs["Volume"], nodes["Material Output"].inputs["Volume"]
    )
    fog.data.materials.append(material)

    black = bpy.data.materials.new("Black")
    black.use_nodes = True
    black.node_tree.nodes["Principled BSDF"].inputs["Base Color"].default_value = (0, 0, 0, 1)
    black.node_tree.nodes["Principled BSDF"].inputs["Specular IOR Level"].default_value = 0.0
    for name, vertices in spec["occluders"].items():
        mesh = bpy.data.meshes.new(name)
        mesh.from_pydata(vertices, [], [[0, 1, 2, 3]])
        obj = bpy.data.objects.new(name, mesh)
        obj.data.materials.append(black)
        scene.collection.objects.link(obj)

    world = bpy.data.worlds.new("World")
    world.use_nodes = True
    world.node_tree.nodes["Background"].inputs["Strength"].default_value = 0.0
    scene.world = world

    scene.render.engine = "CYCLES"
    scene.cycles.device = "CPU"
    scene.cycles.samples = spec["samples"]
    scene.cycles.use_denoising = False
    scene.cycles.use_adaptive_sampling = False
    scene.cycles.max_bounces = 0
    scene.cycles.volume_bounces = 0
    scene.cycles.filter_width = 0.01
    scene.cycles.seed = 1
    scene.render.resolution_x = spec["width"]
    scene.render.resolution_y = spec["height"]
    scene.render.resolution_percentage = 100
    settings = scene.render.image_settings
    settings.file_format = "OPEN_EXR"
    settings.color_depth = "32"
    settings.color_mode = "RGBA"
    scene.render.filepath = spec["out"]
    bpy.ops.render.render(write_still=True)
    """
)


def look_at(eye: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Camera-to-world for a camera at `eye` looking at `target`, world +Z up."""
    back = (eye - target) / np.linalg.norm(eye - target)
    right = np.cross([0.0, 0.0, 1.0], back)
    right /= np.linalg.norm(right)
    up = np.cross(back, right)
    matrix = np.eye(4)
    matrix[:3, 0], matrix[:3, 1], matrix[:3, 2], matrix[:3, 3] = right, up, back, eye
    return matrix


def sun_matrix(travel: np.ndarray) -> np.ndarray:
    """A sun lamp whose -Z axis is the travel direction."""
    back = -travel / np.linalg.norm(travel)
    right = np.cross([0.0, 1.0, 0.0], back)
    right /= np.linalg.norm(right)
    matrix = np.eye(4)
    matrix[:3, 0], matrix[:3, 1], matrix[:3, 2] = right, np.cross(back, right), back
    return matrix


def column_major(matrix: np.ndarray) -> list[float]:
    return [float(v) for v in matrix.T.ravel()]


@pytest.fixture(scope="module")
def setup(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    pytest.importorskip("bpy")
    camera = look_at(np.array([-9.0, -7.0, 3.5]), np.array([0.0, 0.0, 2.2]))
    fog = np.diag([4.0, 3.0, 2.5, 1.0])
    fog[:3, 3] = [0.0, 0.0, 2.5]
    travel = np.array([0.35, 0.2, -1.0])
    # A roof over half the box with a slot in it: shadow, shaft and open sky.
    occluders = {
        "roof_a": [[-6.0, -5.0, 6.0], [0.0, -5.0, 6.0], [0.0, 5.0, 6.0], [-6.0, 5.0, 6.0]],
        "roof_b": [[0.6, -5.0, 6.0], [1.6, -5.0, 6.0], [1.6, 5.0, 6.0], [0.6, 5.0, 6.0]],
    }
    out = tmp_path_factory.mktemp("cycles") / "fog.exr"
    spec = {
        "camera": camera.tolist(),
        "sun": sun_matrix(travel).tolist(),
        "fog": fog.tolist(),
        "occluders": occluders,
        "strength": SUN_STRENGTH,
        "extinction": EXTINCTION,
        "anisotropy": ANISOTROPY,
        "samples": 256,
        "width": WIDTH,
        "height": HEIGHT,
        "out": str(out),
    }
    subprocess.run(
        [sys.executable, "-c", CYCLES_SCRIPT, json.dumps(spec)],
        check=True,
        capture_output=True,
        timeout=600,
    )
    channels = crepuscular.read_exr(out)
    cycles = np.stack([channels[c] for c in "RGB"], axis=-1)
    positions = [p for quad in occluders.values() for p in quad]
    scene = {
        "version": 1,
        "camera": {
            "world_from_camera": column_major(camera),
            "projection": {"kind": "perspective", "focal_length": 50.0, "sensor_width": 36.0},
            "clip_start": 0.1,
            "clip_end": 100.0,
            "width": WIDTH,
            "height": HEIGHT,
        },
        "sun": {"direction": travel.tolist(), "strength": SUN_STRENGTH, "angular_diameter": 0.0},
        "medium": {
            "extinction": EXTINCTION,
            "anisotropy": ANISOTROPY,
            "extent": {"kind": "box", "world_from_cube": column_major(fog)},
        },
        "meshes": [
            {
                "object_id": 2,
                "positions": positions,
                "triangles": [[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7]],
            }
        ],
        "render": {"shadow_map_size": 2048, "steps": 2048, "max_distance": 60.0},
    }
    return {"cycles": cycles, "scene": scene}


@pytest.mark.parametrize("method", ["reference", "minmax"])
def test_box_fog_matches_cycles(setup: dict[str, Any], method: str) -> None:
    scene = json.loads(json.dumps(setup["scene"]))
    scene["render"]["method"] = method
    ours = crepuscular.render(scene).volume[..., :3]
    cycles = setup["cycles"]
    assert cycles.mean() > 1e-3, "Cycles rendered a black image"
    # The image holds fog in shadow, fog in the slot's shaft and fog under open sky.
    luminance = ours.mean(axis=-1)
    inside = luminance > 0
    assert np.ptp(luminance[inside]) > 0.5 * luminance[inside].max()
    # Whole-image mean: Monte Carlo noise averages out, so this is tight.
    assert ours.mean() == pytest.approx(cycles.mean(), rel=0.02)
    # Per pixel, Cycles' 256 samples leave a few percent of noise.
    relative = np.abs(ours - cycles).mean() / cycles.mean()
    assert relative < 0.06, relative
