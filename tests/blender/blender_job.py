"""Cycles renders for the Blender tests, run in a subprocess so that render state never
leaks between tests: `python blender_job.py '<json spec>'`. The extension must already be
installed in the user resources this process inherits; it is enabled here, and every scene
is built and exported through it."""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path
from typing import Any

import bpy
import numpy as np
from mathutils import Matrix, Vector

sys.path.insert(0, str(Path(__file__).resolve().parent))
import blender_scenes


def _render(scene: Any, path: Path, *, animation: bool = False) -> None:
    scene.render.filepath = str(path)
    if animation:
        bpy.ops.render.render(animation=True)
    else:
        bpy.ops.render.render(write_still=True)


def fog_scene(spec: dict[str, Any]) -> Any:
    """The fog box lit through a slotted roof, as in the Cycles reference scene."""
    scene = bpy.context.scene
    blender_scenes.setup_cycles(
        scene, width=spec["width"], height=spec["height"], samples=spec["samples"]
    )
    scene.cycles.filter_width = 0.01
    blender_scenes.add_camera(scene, blender_scenes.look_at((-9, -7, 3.5), (0, 0, 2.2)))
    sun = blender_scenes.add_sun(scene, (0.35, 0.2, -1.0), strength=3.0, enabled=False)
    settings = sun.data.crepuscular
    settings.method, settings.steps, settings.shadow_map_size = "reference", 2048, 2048
    settings.edge_samples, settings.max_distance = 1, 60.0
    fog = np.diag([4.0, 3.0, 2.5, 1.0])
    fog[:3, 3] = [0.0, 0.0, 2.5]
    material = blender_scenes.volume_material(
        "scatter", Color=(1, 1, 1, 1), Density=0.35, Anisotropy=0.3
    )
    blender_scenes.add_fog_box(scene, fog, material)
    black = blender_scenes.black_material(0.0)
    blender_scenes.add_quad(
        scene, "roof_a", [(-6, -5, 6), (0, -5, 6), (0, 5, 6), (-6, 5, 6)], black
    )
    blender_scenes.add_quad(
        scene, "roof_b", [(0.6, -5, 6), (1.6, -5, 6), (1.6, 5, 6), (0.6, 5, 6)], black
    )
    return scene


def job_fidelity(spec: dict[str, Any], out: Path) -> None:
    """Black surfaces: Cycles with its own fog box (shafts off), and our layers of the same
    scene through the operator. Grey variant: a grey backdrop added, Cycles again, then F12
    with shafts on, which composites over a beauty that hides the fog object."""
    scene = fog_scene(spec)
    _render(scene, out / "cycles_black.exr")
    sun = scene.objects["Sun"]
    sun.data.crepuscular.enabled = True
    assert bpy.ops.crepuscular.render_layers(filepath=str(out / "layers.exr")) == {"FINISHED"}
    # The default method, as an artist gets it.
    settings = sun.data.crepuscular
    settings.method = settings.bl_rna.properties["method"].default
    assert settings.method == "prefiltered"
    path = str(out / "layers_default_method.exr")
    assert bpy.ops.crepuscular.render_layers(filepath=path) == {"FINISHED"}
    settings.method = "reference"
    sun.data.crepuscular.enabled = False
    # A grey backdrop outside the box, lit straight by the sun and seen through the fog.
    grey = blender_scenes.black_material(0.5)
    blender_scenes.add_quad(
        scene, "backdrop", [(6, -8, -1), (6, 8, -1), (8, 8, 9), (8, -8, 9)], grey
    )
    _render(scene, out / "cycles_grey.exr")
    sun.data.crepuscular.enabled = True
    scene.crepuscular.write_layers = False
    _render(scene, out / "composite_grey.exr")
    fog = scene.crepuscular.fog_object
    assert fog.visible_camera, "the fog object was not restored"
    assert fog.visible_shadow, "the fog object was not restored"


def job_region_fidelity(spec: dict[str, Any], out: Path) -> None:
    """The fidelity scene through a render region (an odd 53 x 27 of 96 x 54), cropped to
    it and in its frame: Cycles renders each as F12 does, then the operator, which renders
    what F12 renders, our reference and default-method layers."""
    scene = fog_scene(spec)
    render = scene.render
    render.use_border = True
    render.border_min_x, render.border_max_x = 0.3, 0.85
    render.border_min_y, render.border_max_y = 0.2, 0.7
    settings = scene.objects["Sun"].data.crepuscular
    for name, crop in (("cropped", True), ("framed", False)):
        render.use_crop_to_border = crop
        settings.enabled = False
        _render(scene, out / f"cycles_{name}.exr")
        settings.enabled = True
        for method in ("reference", settings.bl_rna.properties["method"].default):
            settings.method = method
            path = str(out / f"{name}_{method}.exr")
            assert bpy.ops.crepuscular.render_layers(filepath=path) == {"FINISHED"}
        settings.method = "reference"


def job_mapped_fidelity(spec: dict[str, Any], out: Path) -> None:
    """The mappings the fidelity scene leaves at their plainest, against Cycles: a tinted
    Principled Volume with an absorption colour (its extinction coloured), a sun with
    colour, temperature, exposure and a disc, and three cameras: orthographic with lens
    shift and a vertical sensor fit, a pinhole inside the box, and a pinhole through 2:1
    anamorphic pixels (the render's pixel aspect). Black surfaces and
    world, no bounces; each view is rendered by Cycles, then as our reference and
    default-method layers."""
    scene = bpy.context.scene
    blender_scenes.setup_cycles(
        scene, width=spec["width"], height=spec["height"], samples=spec["samples"]
    )
    scene.cycles.filter_width = 0.01
    sun = blender_scenes.add_sun(scene, (-0.4, 0.3, -1.0), strength=2.0, enabled=False)
    light = sun.data
    light.color, light.exposure, light.angle = (1.0, 0.85, 0.7), 0.5, math.radians(3.0)
    light.use_temperature, light.temperature = True, 5000.0
    settings = light.crepuscular
    settings.method, settings.steps, settings.shadow_map_size = "reference", 2048, 2048
    settings.edge_samples, settings.max_distance = 1, 80.0
    fog = np.diag([5.0, 4.0, 3.0, 1.0])
    fog[:3, :3] = np.array(Matrix.Rotation(0.3, 3, "Z")) @ fog[:3, :3]
    fog[:3, 3] = [0.0, 0.0, 3.0]
    material = blender_scenes.volume_material(
        "principled",
        Color=(0.9, 0.6, 0.35, 1.0),
        Density=0.3,
        Anisotropy=0.45,
        **{"Absorption Color": (0.2, 0.4, 0.6, 1.0)},
    )
    blender_scenes.add_fog_box(scene, fog, material)
    black = blender_scenes.black_material(0.0)
    blender_scenes.add_quad(
        scene, "ground", [(-30, -30, 0), (30, -30, 0), (30, 30, 0), (-30, 30, 0)], black
    )
    for index, x in enumerate((-4.0, -1.5, 1.0, 3.5)):
        slat = [(x, -5, 7), (x + 1.4, -5, 7), (x + 1.4, 5, 7), (x, 5, 7)]
        blender_scenes.add_quad(scene, f"slat_{index}", slat, black)
    bpy.ops.mesh.primitive_cube_add(size=1.0, location=(1.5, -1.0, 2.5), scale=(0.5, 0.5, 5.0))
    bpy.context.active_object.data.materials.append(black)
    views = {
        "orthographic": blender_scenes.look_at((-14, -12, 9), (0, 0, 2.5)),
        "inside": blender_scenes.look_at((-3.5, -2.0, 1.2), (3, 2, 3.5)),
        "anamorphic": blender_scenes.look_at((-12, -6, 4.5), (0, 0, 3.0)),
    }
    for name, matrix in views.items():
        camera = blender_scenes.add_camera(scene, matrix, lens=24.0)
        if name == "orthographic":
            camera.data.type, camera.data.ortho_scale = "ORTHO", 11.0
            camera.data.sensor_fit = "VERTICAL"
            camera.data.shift_x, camera.data.shift_y = 0.1, -0.05
        elif name == "inside":
            camera.data.shift_y = 0.08
        else:
            camera.data.lens, camera.data.shift_x = 40.0, -0.04
            scene.render.pixel_aspect_x, scene.render.pixel_aspect_y = 2.0, 1.0
        light.crepuscular.enabled = False
        _render(scene, out / f"cycles_{name}.exr")
        light.crepuscular.enabled = True
        for method in ("reference", settings.bl_rna.properties["method"].default):
            settings.method = method
            path = str(out / f"{name}_{method}.exr")
            assert bpy.ops.crepuscular.render_layers(filepath=path) == {"FINISHED"}
        settings.method = "reference"
        scene.render.pixel_aspect_x = scene.render.pixel_aspect_y = 1.0


def _cycles_then_ours(scene: Any, out: Path) -> Any:
    """Cycles' `cycles.exr` with shafts off, then our `reference.exr` and `default.exr`
    (the default method, which it leaves set); returns the sun's settings."""
    _render(scene, out / "cycles.exr")
    settings = scene.objects["Sun"].data.crepuscular
    settings.enabled = True
    assert bpy.ops.crepuscular.render_layers(filepath=str(out / "reference.exr")) == {"FINISHED"}
    settings.method = settings.bl_rna.properties["method"].default
    assert bpy.ops.crepuscular.render_layers(filepath=str(out / "default.exr")) == {"FINISHED"}
    return settings


def job_cutout_fidelity(spec: dict[str, Any], out: Path) -> None:
    """The fidelity scene's fog box under a roof of two leaf-card-like quads cut by an
    image's alpha, one through a Principled BSDF's Alpha and one through a Mix Shader with
    a Transparent BSDF: Cycles, our layers (reference and default method), and our layers
    with the cards made opaque."""
    scene = fog_scene(spec)
    for name in ("roof_a", "roof_b"):
        bpy.data.objects.remove(scene.objects[name])
    image = blender_scenes.alpha_image("Stripes")
    corners_a = [(-6, -5, 6), (0, -5, 6), (0, 5, 6), (-6, 5, 6)]
    corners_b = [(0, -5, 6.2), (5, -5, 6.2), (5, 5, 6.2), (0, 5, 6.2)]
    principled = blender_scenes.cutout_material(image, "principled")
    mixed = blender_scenes.cutout_material(image, "mix")
    blender_scenes.add_card(scene, "card_a", corners_a, principled, 3.0)
    blender_scenes.add_card(scene, "card_b", corners_b, mixed, 2.0)
    _cycles_then_ours(scene, out)
    for name in ("card_a", "card_b"):
        scene.objects[name].data.materials[0] = blender_scenes.black_material(0.0)
    assert bpy.ops.crepuscular.render_layers(filepath=str(out / "opaque.exr")) == {"FINISHED"}


#: The Mapping nodes of two of `job_extension_fidelity`'s cards, each a chain of (vector
#: type, location, rotation, scale), the node nearest the texture first.
MAPPINGS = {
    "extend": [("TEXTURE", (0.2, -0.1, 0.0), (0.0, 0.0, 1.0), (0.8, 1.3, 1.0))],
    "mirror": [
        ("VECTOR", (0.0, 0.0, 0.0), (0.3, 0.0, 0.0), (1.0, 1.0, 1.0)),
        ("POINT", (0.1, -0.3, 0.0), (0.0, 0.0, -1.1), (1.7, 0.9, 1.0)),
    ],
}


def job_extension_fidelity(spec: dict[str, Any], out: Path) -> None:
    """The fidelity scene's fog box under a roof of five cards whose u runs from -0.5 to
    1.5, so that each reads its image past the edges as its Image Texture's extension says:
    Clip (through a Principled BSDF's Alpha, and through a Mix Shader towards a Transparent
    BSDF, whose clipped factor 0 is opaque), Extend and Mirror of the stripes image (their
    coordinates mapped by Mapping nodes, `MAPPINGS`), and a coarse image of scattered solid
    texels read with Closest interpolation. Cycles, our layers
    (reference and default method), and our layers with every texture repeating and
    linear, as they were read before extensions and interpolation were."""
    scene = fog_scene(spec)
    for name in ("roof_a", "roof_b"):
        bpy.data.objects.remove(scene.objects[name])
    stripes = blender_scenes.alpha_image("Stripes")
    # Solid texels with no solid neighbour: linear filtering rounds each into a blob of 61%
    # of its area, where Closest keeps the whole texel.
    dots = bpy.data.images.new("Dots", 4, 4, alpha=True, float_buffer=True)
    rgba = np.zeros((4, 4, 4), dtype=np.float32)
    for row, column in ((0, 0), (1, 2), (2, 1), (3, 3)):
        rgba[row, column, 3] = 1.0
    dots.pixels.foreach_set(rgba.ravel())
    dots.pack()
    cards = [
        ("clip", stripes, "principled", "CLIP", "Linear"),
        ("clip_inverted", stripes, "inverted", "CLIP", "Linear"),
        ("extend", stripes, "principled", "EXTEND", "Linear"),
        ("mirror", stripes, "principled", "MIRROR", "Linear"),
        ("closest", dots, "principled", "REPEAT", "Closest"),
    ]
    textures = []
    for k, (name, image, kind, extension, interpolation) in enumerate(cards):
        material = blender_scenes.cutout_material(image, kind)
        texture = next(n for n in material.node_tree.nodes if n.bl_idname == "ShaderNodeTexImage")
        texture.extension, texture.interpolation = extension, interpolation
        textures.append(texture)
        if name in MAPPINGS:
            blender_scenes.map_texture(material, texture, MAPPINGS[name])
        x0, x1 = -6 + 2.2 * k, -6 + 2.2 * (k + 1)
        corners = [(x0, -5, 6), (x1, -5, 6), (x1, 5, 6), (x0, 5, 6)]
        blender_scenes.add_card(scene, name, corners, material, 1.5, start=-0.5)
    _cycles_then_ours(scene, out)
    for texture in textures:
        texture.extension, texture.interpolation = "REPEAT", "Linear"
    assert bpy.ops.crepuscular.render_layers(filepath=str(out / "repeating.exr")) == {"FINISHED"}


def job_alpha_chain_fidelity(spec: dict[str, Any], out: Path) -> None:
    """The fidelity scene's fog box under a roof of three cards of one smooth alpha (round
    blobs), each through value nodes that sharpen it into a binary alpha, as Blender 4.2
    versions EEVEE's Alpha Clip materials and as artists crisp a leaf: a Math node Greater
    Than 0.3 into a Principled BSDF's Alpha; the image's Color through a constant Color Ramp
    (white from 0.6 up) into a Mix Shader's factor from a Transparent BSDF; and an Invert
    then a Math node Less Than 0.45 into the factor of a Mix Shader towards one. Cycles, our
    layers (reference and default method), and ours with the value nodes muted (each passes
    its input on), as the raw alpha cut at one half."""
    scene = fog_scene(spec)
    for name in ("roof_a", "roof_b"):
        bpy.data.objects.remove(scene.objects[name])
    image = bpy.data.images.new("Blobs", 64, 64, alpha=True, float_buffer=True)
    y, x = np.mgrid[0:64, 0:64] + 0.5
    rgba = np.zeros((64, 64, 4), dtype=np.float32)
    rgba[..., :3] = rgba[..., 3:] = (
        0.5 + 0.5 * np.sin(2 * np.pi * x / 32) * np.sin(2 * np.pi * y / 32)
    )[..., None]
    image.pixels.foreach_set(rgba.ravel())
    image.pack()
    chained = []
    for k, kind in enumerate(("principled", "mix", "inverted")):
        material = blender_scenes.cutout_material(image, kind)
        nodes, links = material.node_tree.nodes, material.node_tree.links
        texture = nodes["Image Texture"]
        target = next(iter(texture.outputs["Alpha"].links)).to_socket
        if kind == "principled":
            step = nodes.new("ShaderNodeMath")
            step.operation, step.inputs[1].default_value = "GREATER_THAN", 0.3
            links.new(texture.outputs["Alpha"], step.inputs[0])
            links.new(step.outputs[0], target)
            chain = [step]
        elif kind == "mix":
            ramp = nodes.new("ShaderNodeValToRGB")
            ramp.color_ramp.interpolation = "CONSTANT"
            ramp.color_ramp.elements[1].position = 0.6
            links.new(texture.outputs["Color"], ramp.inputs["Fac"])
            links.new(ramp.outputs["Color"], target)
            chain = [ramp]
        else:
            invert = nodes.new("ShaderNodeInvert")
            step = nodes.new("ShaderNodeMath")
            step.operation, step.inputs[1].default_value = "LESS_THAN", 0.45
            links.new(texture.outputs["Alpha"], invert.inputs["Color"])
            links.new(invert.outputs["Color"], step.inputs[0])
            links.new(step.outputs[0], target)
            chain = [invert, step]
        chained += chain
        x0, x1 = -6 + 11 / 3 * k, -6 + 11 / 3 * (k + 1)
        corners = [(x0, -5, 6), (x1, -5, 6), (x1, 5, 6), (x0, 5, 6)]
        blender_scenes.add_card(scene, f"card_{kind}", corners, material, 3.0)
    _cycles_then_ours(scene, out)
    for node in chained:
        node.mute = True
    assert bpy.ops.crepuscular.render_layers(filepath=str(out / "unchained.exr")) == {"FINISHED"}


def job_hair_fidelity(spec: dict[str, Any], out: Path) -> None:
    """The fidelity scene's fog box under a roof of hair strands (curves of radius 0.15,
    bending along y) instead of slats: Cycles, and our layers (reference and default
    method)."""
    scene = fog_scene(spec)
    for name in ("roof_a", "roof_b"):
        bpy.data.objects.remove(scene.objects[name])
    y = np.linspace(-5, 5, 9)
    strands = [np.c_[np.full_like(y, x), y, 6 + 0.3 * np.sin(y + x)] for x in np.arange(-6, 5, 0.7)]
    blender_scenes.add_hair(scene, "strands", strands, 0.15, blender_scenes.black_material(0.0))
    # A ground under the box, so that the frame without strands still has geometry.
    ground = [(-30, -30, -0.01), (30, -30, -0.01), (30, 30, -0.01), (-30, 30, -0.01)]
    blender_scenes.add_quad(scene, "ground", ground, blender_scenes.black_material(0.0))
    settings = _cycles_then_ours(scene, out)
    scene.objects["strands"].hide_render = True
    settings.method = "reference"
    assert bpy.ops.crepuscular.render_layers(filepath=str(out / "bare.exr")) == {"FINISHED"}


def job_strand_gap_fidelity(spec: dict[str, Any], out: Path) -> None:
    """One straight strand of radius 0.2 along x at z = 3 in a fog box, seen side-on by an
    orthographic camera (2 m tall, looking along +y), under a sun straight above and one
    30 degrees above the horizon across the strand: per sun, Cycles and our reference
    layers with the strand (`cycles_{tilt}.exr`, `ours_{tilt}.exr`) and without it
    (`bare_cycles_{tilt}.exr`, `bare_ours_{tilt}.exr`)."""
    scene = bpy.context.scene
    blender_scenes.setup_cycles(
        scene, width=spec["width"], height=spec["height"], samples=spec["samples"]
    )
    scene.cycles.filter_width = 0.01
    material = blender_scenes.volume_material("scatter", Color=(1, 1, 1, 1), Density=0.3)
    fog = np.diag([4.0, 4.0, 3.0, 1.0])
    fog[2, 3] = 3.0
    blender_scenes.add_fog_box(scene, fog, material)
    black = blender_scenes.black_material(0.0)
    ground = [(-30, -30, -0.01), (30, -30, -0.01), (30, 30, -0.01), (-30, 30, -0.01)]
    blender_scenes.add_quad(scene, "ground", ground, black)
    x = np.linspace(-3.0, 3.0, 9)
    strand = np.c_[x, np.zeros_like(x), np.full_like(x, 3.0)]
    hair = blender_scenes.add_hair(scene, "strand", [strand], 0.2, black)
    camera = blender_scenes.add_camera(scene, blender_scenes.look_at((0, -10, 3), (0, 0, 3)))
    camera.data.type, camera.data.ortho_scale = "ORTHO", 2.0
    camera.data.sensor_fit = "VERTICAL"
    for tilt in (0, 60):
        travel = (0.0, math.sin(math.radians(tilt)), -math.cos(math.radians(tilt)))
        sun = blender_scenes.add_sun(scene, travel, strength=3.0, enabled=False)
        settings = sun.data.crepuscular
        settings.method, settings.steps, settings.shadow_map_size = "reference", 4096, 4096
        settings.edge_samples = 1
        for prefix, shown in (("", True), ("bare_", False)):
            hair.hide_render = not shown
            settings.enabled = False
            _render(scene, out / f"{prefix}cycles_{tilt}.exr")
            settings.enabled = True
            path = str(out / f"{prefix}ours_{tilt}.exr")
            assert bpy.ops.crepuscular.render_layers(filepath=path) == {"FINISHED"}
        bpy.data.objects.remove(sun)


def job_points_fidelity(spec: dict[str, Any], out: Path) -> None:
    """The fidelity scene's fog box under a roof of points (a geometry-nodes point cloud of
    random radii 0.12 to 0.4 on a jittered grid) instead of slats: Cycles, our layers
    (reference and default method), and ours with the points hidden; then, without them,
    Cycles and our layers with one point around the camera."""
    scene = fog_scene(spec)
    for name in ("roof_a", "roof_b"):
        bpy.data.objects.remove(scene.objects[name])
    rng = np.random.default_rng(11)
    x, y = np.meshgrid(np.arange(-6.0, 5.0, 0.8), np.arange(-5.0, 5.0, 0.8))
    centres = np.c_[x.ravel(), y.ravel(), np.full(x.size, 6.0)]
    centres += rng.uniform(-0.25, 0.25, centres.shape)
    radii = rng.uniform(0.12, 0.4, len(centres))
    black = blender_scenes.black_material(0.0)
    blender_scenes.add_points(scene, "points", centres, radii, black)
    ground = [(-30, -30, -0.01), (30, -30, -0.01), (30, 30, -0.01), (-30, 30, -0.01)]
    blender_scenes.add_quad(scene, "ground", ground, black)
    settings = _cycles_then_ours(scene, out)
    scene.objects["points"].hide_render = True
    settings.method = "reference"
    assert bpy.ops.crepuscular.render_layers(filepath=str(out / "bare.exr")) == {"FINISHED"}
    # One point of radius 8 around the camera, reaching into the box: Cycles culls a
    # point's back side, so the camera sees out of it and the fog inside it is lit, while
    # its far side shadows the fog beyond it.
    eye = np.array(scene.camera.matrix_world.translation)
    blender_scenes.add_points(scene, "shell", [eye], [8.0], black)
    settings.enabled = False
    _render(scene, out / "cycles_shell.exr")
    settings.enabled = True
    for method in ("reference", settings.bl_rna.properties["method"].default):
        settings.method = method
        path = str(out / f"shell_{method}.exr")
        assert bpy.ops.crepuscular.render_layers(filepath=path) == {"FINISHED"}


def job_closures_fidelity(spec: dict[str, Any], out: Path) -> None:
    """The fidelity scene's fog as an Add Shader of Volume Scatter and a coloured Volume
    Absorption, a Mix Shader of Volume Scatter and Principled Volume, and Volume
    Coefficients (beside an Emission of strength 0): Cycles and our layers (reference) of
    each."""
    scene = fog_scene(spec)
    fog = scene.crepuscular.fog_object
    scatter = {"Color": (0.9, 0.9, 0.9, 1.0), "Density": 0.3, "Anisotropy": 0.3}
    materials = {
        "added": blender_scenes.volume_graph(
            "add",
            [("scatter", scatter)],
            [("absorption", {"Color": (0.2, 0.5, 0.8, 1.0), "Density": 0.15})],
        ),
        "mixed": blender_scenes.volume_graph(
            "mix",
            [("scatter", scatter)],
            [("principled", {"Density": 0.8, "Anisotropy": 0.3})],
            fac=0.3,
        ),
        "coefficients": blender_scenes.volume_graph(
            "add",
            [
                (
                    "coefficients",
                    {
                        "Absorption Coefficients": (0.05, 0.1, 0.2),
                        "Scatter Coefficients": (0.3, 0.25, 0.2),
                        "Anisotropy": 0.3,
                    },
                )
            ],
            [("emission", {"Strength": 0.0})],
        ),
    }
    settings = scene.objects["Sun"].data.crepuscular
    for name, material in materials.items():
        fog.data.materials[0] = material
        settings.enabled = False
        _render(scene, out / f"cycles_{name}.exr")
        settings.enabled = True
        path = str(out / f"{name}.exr")
        assert bpy.ops.crepuscular.render_layers(filepath=path) == {"FINISHED"}


def job_disc_fidelity(spec: dict[str, Any], out: Path) -> None:
    """The fidelity scene under a sun of an 8° disc, whose penumbrae blur the shafts
    through the roof's slot: Cycles, our layers (reference and default method), and ours
    under a point sun (the disc set to 0°)."""
    scene = fog_scene(spec)
    sun = scene.objects["Sun"]
    sun.data.angle = math.radians(8.0)
    settings = _cycles_then_ours(scene, out)
    settings.method = "reference"
    sun.data.angle = 0.0
    assert bpy.ops.crepuscular.render_layers(filepath=str(out / "point.exr")) == {"FINISHED"}


def job_particle_hair_fidelity(spec: dict[str, Any], out: Path) -> None:
    """The fidelity scene's fog box under a roof of legacy particle hair (an emitter at the
    roof's edge, not rendered, growing 60 hairs 10 long across the box, of radius 6 cm at
    the root tapering to 1.8 cm): Cycles, our layers (reference and default method), and
    ours with the particle system off."""
    scene = fog_scene(spec)
    for name in ("roof_a", "roof_b"):
        bpy.data.objects.remove(scene.objects[name])
    black = blender_scenes.black_material(0.0)
    edge = [(-6, -5, 5.5), (-6, 5, 5.5), (-6, 5, 7.5), (-6, -5, 7.5)]
    emitter = blender_scenes.add_particle_hair(
        scene, "fur", edge, 60, 10.0, radius_scale=0.12, tip_radius=0.3, material=black
    )
    ground = [(-30, -30, -0.01), (30, -30, -0.01), (30, 30, -0.01), (-30, 30, -0.01)]
    blender_scenes.add_quad(scene, "ground", ground, black)
    settings = _cycles_then_ours(scene, out)
    emitter.modifiers["hair"].show_render = False
    emitter.modifiers["hair"].show_viewport = False
    settings.method = "reference"
    assert bpy.ops.crepuscular.render_layers(filepath=str(out / "bare.exr")) == {"FINISHED"}


def job_visibility_fidelity(spec: dict[str, Any], out: Path) -> None:
    """The fidelity scene's fog box, rendered by Cycles and by us (reference) as its objects'
    ray visibility and the sun's shadow linking change: "plain"; "unlinked", a blocker
    collection that excludes a slat; "included", one that includes only the other slat,
    an instanced copy of it (through its instancer) and the fog (Cycles lights no fog that
    the light's shadow linking leaves out); "wall", a card between the camera and the box
    hidden from shadow rays; "ghost", a card over the box hidden from the camera;
    "ghost_light_path" and "wall_light_path", the same two the other way round (the card
    hidden from shadow rays, the wall from the camera) by their materials
    (`blender_scenes.light_path_material`) rather than their ray visibility; and
    "shadowless", the sun's Cast Shadow off."""
    scene = fog_scene(spec)
    sun = scene.objects["Sun"]
    settings = sun.data.crepuscular
    black = blender_scenes.black_material(0.0)
    source = bpy.data.collections.new("slat source")
    copy = blender_scenes.add_quad(
        scene, "copied slat", [(-3, -5, 6.5), (-2, -5, 6.5), (-2, 5, 6.5), (-3, 5, 6.5)], black
    )
    scene.collection.objects.unlink(copy)
    source.objects.link(copy)
    instancer = bpy.data.objects.new("instancer", None)
    instancer.instance_type, instancer.instance_collection = "COLLECTION", source
    instancer.location = (3.0, 0.0, 0.0)
    scene.collection.objects.link(instancer)
    wall = blender_scenes.add_quad(
        scene, "wall", [(-6, -3, 0.5), (-3, -6, 0.5), (-3, -6, 3.5), (-6, -3, 3.5)], black
    )
    wall.hide_render = True

    def both(name: str) -> None:
        settings.enabled = False
        _render(scene, out / f"cycles_{name}.exr")
        settings.enabled = True
        path = str(out / f"ours_{name}.exr")
        assert bpy.ops.crepuscular.render_layers(filepath=path) == {"FINISHED"}

    both("plain")
    blockers = bpy.data.collections.new("blockers")
    sun.light_linking.blocker_collection = blockers

    blender_scenes.set_blockers(blockers, {"roof_b": "EXCLUDE"})
    both("unlinked")
    fog = scene.crepuscular.fog_object.name
    blender_scenes.set_blockers(
        blockers, {"roof_a": "INCLUDE", "instancer": "INCLUDE", fog: "INCLUDE"}
    )
    both("included")
    sun.light_linking.blocker_collection = None
    wall.hide_render = False
    wall.visible_shadow = False
    both("wall")
    wall.hide_render = True
    # Over the lit half of the box, hidden from the camera: only its shadow shows.
    ghost = blender_scenes.add_quad(
        scene, "ghost", [(1, -2, 5.5), (3, -2, 5.5), (3, 2, 5.5), (1, 2, 5.5)], black
    )
    ghost.visible_camera = False
    both("ghost")
    # The other way round, through their materials, as artists hide a surface from some
    # rays (Light Path's Is Shadow Ray or Is Camera Ray into a Mix Shader towards a
    # Transparent BSDF): the card over the box casts nothing, and the wall hides nothing
    # but casts its shadow.
    ghost.visible_camera = True
    ghost.data.materials[0] = blender_scenes.light_path_material("Is Shadow Ray")
    both("ghost_light_path")
    bpy.data.objects.remove(ghost)
    wall.hide_render = False
    wall.visible_shadow = True
    wall.data.materials[0] = blender_scenes.light_path_material("Is Camera Ray")
    both("wall_light_path")
    # A sun that casts no shadows: Cycles traces no shadow rays for it, so nothing blocks
    # it and the fog does not dim it either.
    wall.hide_render = True
    sun.data.use_shadow = False
    both("shadowless")


def shaft_scene(spec: dict[str, Any]) -> Any:
    """A grey ground and a cube under a sun with shafts, in an unbounded medium."""
    scene = bpy.context.scene
    blender_scenes.setup_cycles(
        scene, width=spec["width"], height=spec["height"], samples=spec["samples"]
    )
    world = scene.world.node_tree.nodes["Background"]
    world.inputs["Strength"].default_value = 0.3
    blender_scenes.add_camera(scene, blender_scenes.look_at((0, -12, 4), (0, 0, 2)), lens=35)
    sun = blender_scenes.add_sun(scene, (0.3, 0.4, -1.0), strength=3.0)
    settings = sun.data.crepuscular
    settings.shadow_map_size, settings.edge_samples = 512, 2
    scene.crepuscular.extinction = 0.08
    grey = blender_scenes.black_material(0.5)
    blender_scenes.add_quad(
        scene, "ground", [(-20, -20, 0), (20, -20, 0), (20, 20, 0), (-20, 20, 0)], grey
    )
    bpy.ops.mesh.primitive_cube_add(size=2, location=(0, 0, 4))
    cube = bpy.context.active_object
    cube.data.materials.append(grey)
    return scene


def job_composite(spec: dict[str, Any], out: Path) -> None:
    scene = shaft_scene(spec)
    sun = scene.objects["Sun"].data.crepuscular
    sun.enabled = False
    _render(scene, out / "beauty.exr")
    sun.enabled = True
    _render(scene, out / "composite.exr")
    # Cycles' Depth pass, and our depth sampled at pixel centres like it.
    scene.view_layers[0].use_pass_z = True
    scene.render.image_settings.media_type = "MULTI_LAYER_IMAGE"
    scene.crepuscular.composite = scene.crepuscular.write_layers = False
    _render(scene, out / "passes.exr")
    sun.edge_samples = 1
    assert bpy.ops.crepuscular.render_layers(filepath=str(out / "centres.exr")) == {"FINISHED"}


def job_unwritable_layers(spec: dict[str, Any], out: Path) -> None:
    """F12 where the layer EXR cannot be written (a folder holds its name): the error is
    reported on the scene once the render ends, and the composite is still written."""
    scene = shaft_scene(spec)
    (out / "blocked_crepuscular_0001.exr").mkdir()
    _render(scene, out / "blocked.exr")
    (out / "report.json").write_text(json.dumps({"last_error": scene.crepuscular.last_error}))


def job_animation(spec: dict[str, Any], out: Path) -> None:
    scene = shaft_scene(spec)
    scene.frame_start, scene.frame_end = 1, 3
    settings = scene.objects["Sun"].data.crepuscular
    settings.use_closing = True
    for frame, radius in ((1, 0.0), (3, 3.0)):
        settings.closing_radius = radius
        settings.keyframe_insert("closing_radius", frame=frame)
    camera = scene.camera
    for frame, x in ((1, 0.0), (3, 3.0)):
        camera.location.x = x
        camera.keyframe_insert("location", frame=frame)
    # The cube gets a hole the closing fills as the radius grows.
    cube = scene.objects["Cube"]
    cube.scale = (2.0, 2.0, 0.1)
    hole = cube.modifiers.new("Hole", "BOOLEAN")
    bpy.ops.mesh.primitive_cube_add(size=0.8, location=(0, 0, 4))
    cutter = bpy.context.active_object
    cutter.hide_render = True
    hole.object = cutter
    settings.enabled = False
    _render(scene, out / "beauty_", animation=True)
    settings.enabled = True
    _render(scene, out / "shot_", animation=True)
    # The scripting operator at each frame, for comparison with what the renders wrote.
    for frame in (1, 2, 3):
        scene.frame_set(frame)
        path = out / f"operator_{frame}.exr"
        assert bpy.ops.crepuscular.render_layers(filepath=str(path)) == {"FINISHED"}


def job_silhouette(spec: dict[str, Any], out: Path) -> None:
    """A flat, rotated occluder against the sky seen by an orthographic camera: the layers'
    alpha at its edges against the beauty's alpha there."""
    scene = bpy.context.scene
    blender_scenes.setup_cycles(
        scene, width=spec["width"], height=spec["height"], samples=spec["samples"]
    )
    scene.render.film_transparent = True
    camera = blender_scenes.add_camera(scene, np.eye(4))
    camera.matrix_world = Matrix.Translation((0, -10, 0)) @ Matrix.Rotation(np.pi / 2, 4, "X")
    camera.data.type = "ORTHO"
    camera.data.ortho_scale = 10.0
    quad = blender_scenes.add_quad(
        scene,
        "card",
        [(-2, 0, -1.5), (2, 0, -1.5), (2, 0, 1.5), (-2, 0, 1.5)],
        blender_scenes.black_material(0.5),
    )
    quad.rotation_euler = (0.0, np.radians(23.0), 0.0)
    sun = blender_scenes.add_sun(scene, (1.0, 0.3, -0.5), strength=2.0, enabled=False)
    settings = sun.data.crepuscular
    settings.shadow_map_size, settings.max_distance = 256, 40.0
    scene.crepuscular.extinction = 0.05
    _render(scene, out / "beauty.exr")
    settings.enabled = True
    for samples in spec["edge_samples"]:
        settings.edge_samples = samples
        path = out / f"layers_{samples}.exr"
        assert bpy.ops.crepuscular.render_layers(filepath=str(path)) == {"FINISHED"}


def round_trip_scene(spec: dict[str, Any]) -> Any:
    """Meshes (one arrayed by a modifier and hidden from shadow rays, one that takes holes,
    one left out by the sun's shadow linking, a column posed by an armature), a card cut by
    an alpha mask, hair strands, a point cloud, a camera with a vertical sensor fit, lens
    shift and clip range, a sun with exposure, colour and a styled look (closing, holes, a
    transfer function), and a fog box."""
    scene = bpy.context.scene
    scene.render.resolution_x, scene.render.resolution_y = spec["width"], spec["height"]
    scene.render.resolution_percentage = 100
    scene.render.engine = "CYCLES"
    # The add-on gives its volume layer the beauty's pixel filter; the USD step composites
    # over beauties it never sees rendered and keeps its layers unfiltered. A filter this
    # narrow is no filter, so both write the same layers.
    scene.cycles.filter_width = 0.01
    scene.frame_set(spec.get("frame", 1))
    camera = blender_scenes.add_camera(scene, blender_scenes.look_at((-11, -13, 5), (0, 0, 2.5)))
    lens = camera.data
    lens.lens, lens.sensor_fit, lens.sensor_height = 42.0, "VERTICAL", 20.0
    lens.shift_x, lens.shift_y, lens.clip_start, lens.clip_end = 0.06, -0.04, 0.3, 90.0
    sun = blender_scenes.add_sun(scene, (0.35, 0.25, -1.0), strength=2.5)
    sun.data.exposure, sun.data.color, sun.data.angle = 0.5, (1.0, 0.9, 0.75), 0.05
    settings = sun.data.crepuscular
    settings.shadow_map_size, settings.max_distance = 512, 60.0
    settings.use_closing, settings.closing_radius = True, 0.3
    settings.use_holes, settings.holes_frequency, settings.holes_threshold = True, 0.4, 0.3
    settings.holes_pivot = (1.0, 2.0, 0.0)
    settings.use_tf, settings.tf_mode, settings.tf_depth_far = True, "color", 40.0
    layer = settings.tf_layers.add()
    layer.kind, layer.shape = "gradient", "linear"
    layer.start, layer.end = (0.0, 0.0), (0.0, 1.0)
    for position, color in ((0.0, (1.0, 0.8, 0.6, 1.0)), (1.0, (0.4, 0.6, 1.0, 1.0))):
        stop = layer.stops.add()
        stop.position, stop.color = position, color
    fog = np.diag([7.0, 6.0, 4.0, 1.0])
    fog[:3, 3] = [0.0, 0.0, 4.0]
    material = blender_scenes.volume_material(
        "scatter", Color=(1.0, 0.8, 0.55, 1), Density=0.12, Anisotropy=0.3
    )
    blender_scenes.add_fog_box(scene, fog, material)
    blender_scenes.add_quad(
        scene, "ground", [(-30, -30, 0), (30, -30, 0), (30, 30, 0), (-30, 30, 0)]
    )
    for index, x in enumerate((-5.0, -2.2, 0.6, 3.4)):
        slat = blender_scenes.add_quad(
            scene, f"slat_{index}", [(x, -6, 7), (x + 2, -6, 7), (x + 2, 6, 7.5), (x, 6, 7.5)]
        )
        slat.crepuscular.takes_holes = index == 1
    bpy.ops.mesh.primitive_cube_add(size=1.0, location=(-3.0, 1.0, 1.5))
    arrayed = bpy.context.active_object
    array = arrayed.modifiers.new("Array", "ARRAY")
    array.count, array.relative_offset_displace = 3, (1.8, 0.0, 0.4)
    # Hidden from shadow rays, and a slat left out by the sun's shadow linking: both still
    # hide the fog from the camera. The hook authors them out of the light's shadowLink.
    arrayed.visible_shadow = False
    blockers = bpy.data.collections.new("blockers")
    sun.light_linking.blocker_collection = blockers
    blender_scenes.set_blockers(blockers, {"slat_2": "EXCLUDE"})
    bpy.ops.mesh.primitive_ico_sphere_add(subdivisions=2, radius=1.2, location=(2.5, -1.0, 2.0))
    add_rigged_column(scene)
    # A card cut by a PNG's alpha: Blender's exporter writes a UsdPreviewSurface whose
    # opacity is a UsdUVTexture's alpha, mirrored past its edges, whose coordinates a
    # UsdTransform2d maps as the Mapping node does.
    leaf = blender_scenes.alpha_png(Path(spec["out"]) / "leaf.png")
    card = [(-8.5, -6, 7.2), (-5.2, -6, 7.2), (-5.2, 6, 7.2), (-8.5, 6, 7.2)]
    material = blender_scenes.cutout_material(leaf, "principled")
    texture = next(n for n in material.node_tree.nodes if n.bl_idname == "ShaderNodeTexImage")
    texture.extension = "MIRROR"
    blender_scenes.map_texture(
        material, texture, [("POINT", (0.1, -0.2, 0.0), (0.0, 0.0, 0.4), (1.3, 0.8, 1.0))]
    )
    blender_scenes.add_card(scene, "leaf_card", card, material, 2.0)
    # Two cards cut by Mix Shaders with a Transparent BSDF, whose cuts Blender's exporter
    # drops (it writes opaque UsdPreviewSurfaces): the hook writes each mask beside the
    # stage as the surface's opacity. One is the transparency (inverted), held past its
    # edges and mapped by a rotation and a mirroring scale (a UsdTransform2d); the other
    # the alpha, clipped past its edges and mapped by a tilt out of the UV plane, which
    # shears it (mapped coordinates on the mesh).
    cards = {
        "veil_card": ([(5.5, -6, 6.9), (7.5, -6, 6.9), (7.5, 0, 6.9), (5.5, 0, 6.9)], "inverted"),
        "lattice_card": ([(5.5, 0, 6.9), (7.5, 0, 6.9), (7.5, 6, 6.9), (5.5, 6, 6.9)], "mix"),
    }
    mappings = {
        "veil_card": ("EXTEND", (0.2, 0.1, 0.0), (0.0, 0.0, -0.5), (1.5, -0.7, 1.0)),
        "lattice_card": ("CLIP", (0.1, -0.1, 0.0), (0.6, 0.4, 0.3), (1.2, 1.4, 1.0)),
    }
    for name, (corners, kind) in cards.items():
        material = blender_scenes.cutout_material(blender_scenes.alpha_image(name), kind)
        nodes = material.node_tree.nodes
        texture = next(n for n in nodes if n.bl_idname == "ShaderNodeTexImage")
        extension, location, rotation, scale = mappings[name]
        texture.extension = extension
        blender_scenes.map_texture(material, texture, [("POINT", location, rotation, scale)])
        blender_scenes.add_card(scene, name, corners, material, 3.0)
    # A card over the fog hidden from shadow rays by Light Path, which Blender's exporter
    # cannot carry: the hook leaves it out of the light's shadowLink, as the add-on casts
    # none of it.
    veil = [(1.0, -2.0, 6.8), (3.0, -2.0, 6.8), (3.0, 2.0, 6.8), (1.0, 2.0, 6.8)]
    blender_scenes.add_quad(
        scene, "unshadowed_card", veil, blender_scenes.light_path_material("Is Shadow Ray")
    )
    # Hair strands across the slats' gaps, inside the fog, which the exporter writes as
    # BasisCurves with widths.
    y = np.linspace(-6, 6, 7)
    strands = [np.c_[np.full_like(y, x), y, 6.6 + 0.2 * np.sin(y + x)] for x in (-2.6, 0.2, 3.0)]
    blender_scenes.add_hair(scene, "strands", strands, 0.12, blender_scenes.black_material(0.0))
    # A cloud of motes over the fog, which the exporter writes as Points with widths.
    rng = np.random.default_rng(5)
    motes = np.c_[rng.uniform(-6, 6, (60, 2)), rng.uniform(6.2, 6.9, 60)]
    blender_scenes.add_point_cloud(scene, "motes", motes, rng.uniform(0.1, 0.3, 60))
    # A bevelled Bezier circle and a NURBS sphere in the fog, whose surfaces Blender's
    # exporter does not write (the circle as curves of its path and radius, the sphere not
    # at all): the hook writes their meshes.
    bpy.ops.curve.primitive_bezier_circle_add(radius=1.2, location=(1.0, -3.0, 5.5))
    ring = bpy.context.active_object
    ring.name, ring.data.bevel_depth, ring.rotation_euler = "ring", 0.15, (0.4, 0.2, 0.0)
    bpy.ops.surface.primitive_nurbs_surface_sphere_add(radius=0.7, location=(-1.5, -3.5, 4.5))
    # A Subdivision Surface modifier last, which Blender's exporter writes as the cage with
    # a Catmull-Clark scheme and no level: the hook authors the render levels, and the USD
    # step refines the cage onto its limit surface. Seven-sided caps, and a vertex creased
    # to a corner. Cast as its cage, it reads 0.37% off in red through the region.
    bpy.ops.mesh.primitive_cylinder_add(
        vertices=7, radius=0.9, depth=1.6, location=(3.5, -3.0, 5.0), rotation=(0.5, 0.3, 0.0)
    )
    capsule = bpy.context.active_object
    capsule.name = "capsule"
    corner = capsule.data.attributes.new("crease_vert", "FLOAT", "POINT")
    corner.data[0].value = 1.0
    capsule.modifiers.new("Subdivision", "SUBSURF").render_levels = 2
    # Creased edges under a modifier that ignores creases, which Blender's exporter writes
    # all the same: the hook blocks them (creased, visibility reads 4·10⁻⁴ off, depth
    # 2.7·10⁻⁴; as its cage, 0.18% off in red).
    bpy.ops.mesh.primitive_cube_add(size=1.4, location=(0.3, -1.5, 3.2), rotation=(0.3, 0.6, 0.2))
    pillow = bpy.context.active_object
    pillow.name = "pillow"
    creases = pillow.data.attributes.new("crease_edge", "FLOAT", "EDGE")
    for edge in range(0, 12, 2):
        creases.data[edge].value = 1.0
    smooth = pillow.modifiers.new("Subdivision", "SUBSURF")
    smooth.render_levels, smooth.use_creases = 2, False
    # A subdivided lantern cut by the leaf's alpha, whose texture coordinates the modifier
    # smooths as it smooths the points (*UV Smooth* All, which Blender's exporter writes as
    # faceVaryingLinearInterpolation "none"; the default, Keep Boundaries, smooths them
    # inside each island). Refined linearly instead, they drift by up to 6% of the image:
    # the still reads 0.08% off in blue and alpha, and 4.8 units in depth where cuts move.
    bpy.ops.mesh.primitive_uv_sphere_add(
        segments=8, ring_count=6, radius=1.0, location=(-1.4, -3.0, 3.5), rotation=(0.3, 0.2, 0.5)
    )
    lantern = bpy.context.active_object
    lantern.name = "lantern"
    diagonal = blender_scenes.cutout_material(leaf, "principled")
    texture = next(n for n in diagonal.node_tree.nodes if n.bl_idname == "ShaderNodeTexImage")
    blender_scenes.map_texture(
        diagonal, texture, [("POINT", (0.0, 0.0, 0.0), (0.0, 0.0, 0.8), (2.0, 2.0, 1.0))]
    )
    lantern.data.materials.append(diagonal)
    lantern_smooth = lantern.modifiers.new("Subdivision", "SUBSURF")
    lantern_smooth.render_levels, lantern_smooth.uv_smooth = 2, "SMOOTH_ALL"
    # A slab with a window a Boolean modifier cuts: the faces around the window are
    # concave n-gons, which Blender's exporter writes as they are. The USD step ear-clips
    # them, as Blender triangulates them; fanned, they cover the window and its shaft:
    # the animation's first frame reads 0.17% off in blue, the orthographic view 0.17
    # units off in depth. Tilted, so that no view sees a face of it almost edge on.
    bpy.ops.mesh.primitive_cube_add(size=1.0, location=(0.6, 3.5, 6.0))
    slab = bpy.context.active_object
    slab.name, slab.scale, slab.rotation_euler = "skylight", (3.0, 4.0, 0.2), (-0.35, 0.0, 0.0)
    bpy.ops.mesh.primitive_cube_add(size=1.0, location=(0.62, 3.9, 6.0))
    cutter = bpy.context.active_object
    cutter.name, cutter.scale, cutter.display_type = "skylight_cutter", (0.8, 1.3, 1.0), "BOUNDS"
    cutter.hide_render = True
    cutter.hide_set(True)
    window = slab.modifiers.new("Window", "BOOLEAN")
    window.object, window.operation = cutter, "DIFFERENCE"
    # Legacy particle hair over the fog, which Blender's exporter leaves out by default:
    # the hook adds its curves, with widths.
    blender_scenes.add_particle_hair(
        scene, "fur", [(-4, 1, 6.5), (0, 1, 6.5), (0, 5, 6.5), (-4, 5, 6.5)], 60, 0.8,
        radius_scale=0.2, material=blender_scenes.black_material(0.0),
    )  # fmt: skip
    # Dust that geometry nodes make of a mesh's vertices, which Blender's exporter writes
    # as an empty mesh: the hook adds its Points.
    dust = np.c_[rng.uniform(-5, 5, (40, 2)), rng.uniform(4.5, 6.0, 40)]
    blender_scenes.add_points(
        scene, "dust", dust, rng.uniform(0.15, 0.35, 40), blender_scenes.black_material(0.0)
    )
    return scene


def add_rigged_column(scene: Any) -> Any:
    """A column skinned to a two-bone armature and posed, its upper bone bent 65° and its
    lower leaning 15°; a ring of vertices halfway between the bones is weighted to both.
    Returns the armature. Blender's USD exporter writes it as a UsdSkel rest shape, bind
    and pose, which the USD step must pose again to cast the same shadow."""
    data = bpy.data.armatures.new("Rig")
    rig = bpy.data.objects.new("Rig", data)
    scene.collection.objects.link(rig)
    rig.location = (4.5, 2.5, 0.0)
    bpy.context.view_layer.objects.active = rig
    bpy.ops.object.mode_set(mode="EDIT")
    lower = data.edit_bones.new("lower")
    lower.head, lower.tail = (0.0, 0.0, 0.0), (0.0, 0.0, 2.5)
    upper = data.edit_bones.new("upper")
    upper.head, upper.tail, upper.parent = (0.0, 0.0, 2.5), (0.0, 0.0, 5.0), lower
    bpy.ops.object.mode_set(mode="OBJECT")
    bpy.ops.mesh.primitive_cylinder_add(
        vertices=12, radius=0.5, depth=5.0, location=(4.5, 2.5, 2.5)
    )
    column = bpy.context.active_object
    bpy.ops.object.mode_set(mode="EDIT")
    bpy.ops.mesh.select_all(action="SELECT")
    bpy.ops.mesh.subdivide(number_cuts=3)
    bpy.ops.object.mode_set(mode="OBJECT")
    column.parent = rig
    column.matrix_parent_inverse = rig.matrix_world.inverted()
    column.modifiers.new("Armature", "ARMATURE").object = rig
    # Subdivided after skinning, which the export writes as a skinned cage: the USD step
    # poses the cage, then refines it (cast as its cage, 0.41% off in red).
    column.modifiers.new("Subdivision", "SUBSURF").render_levels = 1
    groups = [column.vertex_groups.new(name=name) for name in ("lower", "upper")]
    for vertex in column.data.vertices:
        on_upper = min(max(vertex.co.z + 0.5, 0.0), 1.0)  # 0 below the middle, 1 above
        for group, weight in zip(groups, (1.0 - on_upper, on_upper), strict=True):
            if weight > 0.0:
                group.add([vertex.index], weight, "REPLACE")
    for name, angles in (("lower", (0.0, 15.0, 0.0)), ("upper", (65.0, 0.0, 0.0))):
        bone = rig.pose.bones[name]
        bone.rotation_mode = "XYZ"
        bone.rotation_euler = [math.radians(a) for a in angles]
    return rig


def job_usd_round_trip(spec: dict[str, Any], out: Path) -> None:
    """The add-on's layers, and the same scene through Blender's USD exporter (default
    options, and again Y up in centimetres); the still also through a render region, in
    its frame, which the export carries as the render settings' data window. Animated:
    through 3:2 anamorphic pixels, camera, lens, sun and closing radius keyed over frames
    1-3, and the fog box left out of the export. Orthographic: the still's camera turned
    orthographic (16 units across its vertical fit, its shift kept), through 4:5 pixels,
    without a region. Shadowless: the still with the sun's Cast Shadow off, without a
    region or the second export."""
    scene = round_trip_scene(spec)
    if spec.get("shadowless"):
        scene.objects["Sun"].data.use_shadow = False
    if spec.get("orthographic"):
        scene.camera.data.type = "ORTHO"
        scene.camera.data.ortho_scale = 16.0
        scene.render.pixel_aspect_y = 1.25
    frames = [scene.frame_current]
    if spec["animated"]:
        scene.render.pixel_aspect_x = 1.5
        scene.frame_start, scene.frame_end = 1, 3
        frames = [1, 2, 3]
        camera, sun, rig = scene.camera, scene.objects["Sun"], scene.objects["Rig"]
        # A shape key, keyed: Blender exports shape keys as blend shapes, and their
        # weights only with the animation.
        bpy.ops.mesh.primitive_cube_add(size=1.5, location=(-1.0, 3.0, 1.0))
        stretched = bpy.context.active_object
        stretched.shape_key_add(name="Basis")
        shape = stretched.shape_key_add(name="Tall")
        for point in shape.data:
            point.co.z *= 4.0
        settings = sun.data.crepuscular
        start, aim = camera.location.copy(), sun.rotation_euler.copy()
        keys = ((0.0, 42.0, 0.0, 0.1), (1.5, 50.0, 0.15, 0.4), (3.0, 35.0, 0.3, 0.8))
        for frame, (shift, lens, tilt, radius) in zip(frames, keys, strict=True):
            camera.location = start + Vector((shift, 0.0, 0.0))
            camera.keyframe_insert("location", frame=frame)
            camera.data.lens = lens
            camera.data.keyframe_insert("lens", frame=frame)
            sun.rotation_euler.y = aim.y + tilt
            sun.keyframe_insert("rotation_euler", frame=frame)
            settings.closing_radius = radius
            settings.keyframe_insert("closing_radius", frame=frame)
            bend = rig.pose.bones["upper"]
            bend.rotation_euler.x = math.radians(65.0 - 40.0 * shift)
            bend.keyframe_insert("rotation_euler", frame=frame)
            shape.value = shift / 3.0
            shape.keyframe_insert("value", frame=frame)
        scene.crepuscular.fog_object.hide_render = True  # the exporter leaves it out
    for frame in frames:
        scene.frame_set(frame)
        path = out / f"blender.{frame:04d}.exr"
        assert bpy.ops.crepuscular.render_layers(filepath=str(path)) == {"FINISHED"}
    scene.frame_set(frames[0])
    if not spec["animated"] and not spec.get("orthographic") and not spec.get("shadowless"):
        render = scene.render
        render.use_border, render.use_crop_to_border = True, False
        # 24.96 to 74.88 of 96 columns: Blender renders columns 24 to 73 (it truncates),
        # where the centres inside those fractions are 25 to 74.
        render.border_min_x, render.border_max_x = 0.26, 0.78
        render.border_min_y, render.border_max_y = 0.1, 0.6
        path = out / f"blender_region.{frames[0]:04d}.exr"
        assert bpy.ops.crepuscular.render_layers(filepath=str(path)) == {"FINISHED"}
    animation = {"export_animation": True} if spec["animated"] else {}
    assert bpy.ops.wm.usd_export(filepath=str(out / "shot.usda"), **animation) == {"FINISHED"}
    if not spec["animated"] and not spec.get("shadowless"):
        assert bpy.ops.wm.usd_export(
            filepath=str(out / "shot_y_up_cm.usda"),
            convert_orientation=True,
            export_global_up_selection="Y",
            export_global_forward_selection="NEGATIVE_Z",
            convert_scene_units="CENTIMETERS",
        ) == {"FINISHED"}


JOBS = {
    "fidelity": job_fidelity,
    "mapped_fidelity": job_mapped_fidelity,
    "region_fidelity": job_region_fidelity,
    "cutout_fidelity": job_cutout_fidelity,
    "extension_fidelity": job_extension_fidelity,
    "alpha_chain_fidelity": job_alpha_chain_fidelity,
    "hair_fidelity": job_hair_fidelity,
    "points_fidelity": job_points_fidelity,
    "strand_gap_fidelity": job_strand_gap_fidelity,
    "closures_fidelity": job_closures_fidelity,
    "disc_fidelity": job_disc_fidelity,
    "particle_hair_fidelity": job_particle_hair_fidelity,
    "visibility_fidelity": job_visibility_fidelity,
    "composite": job_composite,
    "animation": job_animation,
    "silhouette": job_silhouette,
    "usd_round_trip": job_usd_round_trip,
    "unwritable_layers": job_unwritable_layers,
}


def main() -> None:
    spec = json.loads(sys.argv[1])
    blender_scenes.reset()
    out = Path(spec["out"])
    out.mkdir(parents=True, exist_ok=True)
    JOBS[spec["job"]](spec, out)


if __name__ == "__main__":
    main()
