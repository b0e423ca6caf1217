"""Our layers against Cycles on random fog-box scenes: a search for differences from an
independent renderer.

Each case builds a scene in Blender through the installed extension: random meshes (those
of `differential_views.py --geometry random`), black under a black world; a box of fog, a
Volume Scatter or a Principled Volume with an absorption colour, at random density and
anisotropy; a sun with a random colour, temperature or exposure; and a camera outside the
box or inside it, sometimes orthographic, with lens shift or a sensor fit, sometimes
looking past the box towards the sun. Cycles renders it twice, with two seeds and no
bounces, so that its image is the single-scattered light alone; the extension renders our
layers with `reference`, `minmax` and the default method. Printed per case: Cycles' mean
and its noise (half the two renders' difference), then per method its mean over Cycles'
and its error, the mean absolute difference of 4x4-pixel block means over Cycles' mean
(blocks, so that Cycles' noise stays well under it). Each case's folder keeps the renders
and the reference's inputs as `scene.json`, for `crepuscular render --scene` without
Blender.

    .venv/bin/python examples/cycles_views.py --seed 3 --cases 30

The extension is built from the wheel in `dist/` (after `make demo` or `make test`) and
installed into a temporary Blender user folder, as the tests install it. Fog is
grey unless `--tinted`: Cycles colours a tinted fog's extinction per channel, and the
extension then has crepuscular scatter once per channel value. `--cutouts` adds one to three
cards over the box cut by a random image's alpha (stripes, checks or round holes, through a
Principled BSDF's Alpha or a Mix Shader with a Transparent BSDF either side; repeating or
not, read with any extension and Linear or Closest, now and then through a Mapping node),
which crepuscular reads as alpha masks (`scene.json` carries them as `alpha_mask` images
beside it). `--hair` adds a
hair curves object of 10 to 40 black strands over the box, which the extension draws as ribbons,
and `--points` a geometry-nodes point cloud of 20 to 300 black points of random radii over
and in the box, which it draws as spheres (`scene.json` carries both as meshes).
`--closures` builds each fog of several volume closures: an Add or Mix Shader of it and a
Volume Absorption, or Volume Coefficients. Views that see no fog print as black. A sun's
disc is left at 0° (a point sun), or with `--disc` drawn from 1° to 10°, which the extension
softens over `crepuscular.SUN_DISC_SAMPLES` directions. `--grouped` rebuilds the fog's and
the cards' materials inside node groups, as asset libraries ship them, with inputs exposed
and given outside by sockets, Value and RGB nodes, and reached through reroutes and muted
Add Shaders (the same scenes as without it, seed for seed). `--anamorphic` renders each
case through non-square pixels, 1:2 to 2:1, and `--region` through a random render region,
cropped to it or not (both the same scenes, seed for seed). `--usd` also exports each case
with Blender's USD exporter (the extension's hook authoring the shaft settings and the
RenderSettings) and renders the stage with `crepuscular-usd`: its error against Cycles is
printed as `usd`, and its largest mean relative difference per layer from the extension's
own reference layers (the method the hook exports) as `usd vs ours`, which the round
trip's test bounds by 1e-4 and which flags above 1e-3. With `--usd`, `--points` makes
half the clouds Point Cloud objects rather than geometry nodes' (Blender's exporter writes
an object's own points, and the extension's hook a modifier's). `--curves` adds one to
three black shapes that are not meshes (bevelled Bezier circles, extruded text, NURBS
spheres; the same scenes otherwise, seed for seed). `--subdivided` adds one to three black
meshes under a Subdivision Surface modifier (cubes, cylinders, icospheres, open grids; 1 to
3 render levels, creased edges and vertices now and then; the same scenes otherwise), which
Blender's exporter writes as cages and the hook tags with their levels; with `--cutouts`
too, most of them are cut by a random alpha through their UV maps, under a random *UV
Smooth*. `--fur` adds a
legacy particle-hair emitter of 50 to 400 black hairs (which Blender's exporter leaves out
and the hook writes as curves with widths). `--booleans` adds one or two black walls or
slabs with one to three windows each that a Boolean modifier cuts, whose faces around the
windows are concave n-gons (the same scenes otherwise, seed for seed). `--shadowless` turns
the sun's Cast Shadow off: Cycles traces no shadow rays for it, so nothing blocks it and the
fog does not dim it (the same scenes otherwise).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import random
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
os.environ["BLENDER_USER_RESOURCES"] = tempfile.mkdtemp(prefix="crepuscular-cycles-views-")

import bpy  # noqa: E402
import numpy as np  # noqa: E402
from mathutils import Euler  # noqa: E402

import crepuscular  # noqa: E402

sys.path.insert(0, str(ROOT / "tests" / "blender"))
import blender_scenes  # noqa: E402
from differential_views import random_geometry  # noqa: E402

METHODS = ("reference", "minmax", "default")
#: The USD step's largest mean relative difference per layer from the extension's own
#: layers above which a case is flagged: ten times the round trip test's bound.
USD_FLAG = 1e-3
USD_LAYERS = ("volume.R", "volume.G", "volume.B", "volume.A", "visibility")


def random_fog(
    rng: random.Random, tinted: bool, closures: bool = False
) -> tuple[bpy.types.Material, str]:
    """A Volume Scatter or Principled Volume of random density, anisotropy and colour; with
    `closures`, built of several closures instead (`combined_fog`)."""
    grey = rng.uniform(0.3, 1.0)
    colour = (grey, grey, grey, 1.0)
    if tinted:
        colour = (rng.uniform(0.4, 1.0), rng.uniform(0.4, 1.0), rng.uniform(0.4, 1.0), 1.0)
    density = math.exp(rng.uniform(math.log(0.03), math.log(0.6)))
    anisotropy = rng.uniform(-0.3, 0.8)
    inputs = {"Color": colour, "Density": density, "Anisotropy": anisotropy}
    kind = "scatter"
    if rng.random() < 0.4:
        kind = "principled"
        absorption = rng.uniform(0.0, 1.0)
        inputs["Absorption Color"] = (absorption, absorption, absorption, 1.0)
    label = f"{kind} density {density:.3f} g {anisotropy:+.2f}"
    if closures:
        return combined_fog(rng, tinted, kind, inputs, label)
    return blender_scenes.volume_material(kind, **inputs), label


def combined_fog(
    rng: random.Random, tinted: bool, kind: str, inputs: dict, label: str
) -> tuple[bpy.types.Material, str]:
    """The fog `kind` with `inputs` plus a Volume Absorption (an Add Shader), mixed with
    one (a Mix Shader of random factor), or as Volume Coefficients of the same scattering
    and an absorption."""
    grey = rng.uniform(0.1, 0.9)
    absorbing = (grey, grey, grey, 1.0)
    if tinted:
        absorbing = (rng.uniform(0.1, 0.9), rng.uniform(0.1, 0.9), rng.uniform(0.1, 0.9), 1.0)
    absorption = {"Color": absorbing, "Density": inputs["Density"] * rng.uniform(0.2, 1.0)}
    combine = rng.choice(["add", "mix", "coefficients"])
    if combine == "coefficients":
        scattering = [inputs["Density"] * c for c in inputs["Color"][:3]]
        absorbed = [absorption["Density"] * (1 - c) for c in absorbing[:3]]
        coefficients = {
            "Scatter Coefficients": scattering,
            "Absorption Coefficients": absorbed,
            "Anisotropy": inputs["Anisotropy"],
        }
        material = blender_scenes.volume_graph(
            "add", [("coefficients", coefficients)], [("emission", {"Strength": 0.0})]
        )
        return (
            material,
            f"coefficients density {inputs['Density']:.3f} g {inputs['Anisotropy']:+.2f}",
        )
    fac = rng.uniform(0.2, 0.8)
    material = blender_scenes.volume_graph(
        combine, [(kind, inputs)], [("absorption", absorption)], fac=fac
    )
    mixed = f" fac {fac:.2f}" if combine == "mix" else ""
    return material, f"{label} {combine} absorption {absorption['Density']:.3f}{mixed}"


def random_alpha(rng: random.Random, size: int = 128) -> np.ndarray:
    """A (size, size) cutout alpha: stripes, checks, or a solid sheet with round holes.
    Features span 8 texels or more, as in a real leaf's mask: where they span two, half the
    mask lies in the one-texel ramps of bilinear filtering, which Cycles reads as partial
    shadow and crepuscular clips at one half (3.4% apart in 4x4 blocks on such a checker)."""
    y, x = np.mgrid[0:size, 0:size] + 0.5
    width = rng.randint(8, 32)
    kind = rng.choice(["stripes", "checks", "holes"])
    if kind == "stripes":
        return ((x // width) % 2).astype(np.float32)
    if kind == "checks":
        return ((x // width + y // width) % 2).astype(np.float32)
    alpha = np.ones((size, size), dtype=np.float32)
    for _ in range(rng.randint(2, 6)):
        cx, cy, r = rng.uniform(0, size), rng.uniform(0, size), rng.uniform(8, size / 4)
        alpha[(x - cx) ** 2 + (y - cy) ** 2 < r**2] = 0.0
    return alpha


def random_cutout(rng: random.Random, name: str) -> bpy.types.Material:
    """A black material cut by a random alpha: through a Principled BSDF's Alpha or a Mix
    Shader with a Transparent BSDF either side, read with any extension and Linear or
    Closest, now and then through a Mapping node."""
    alpha = random_alpha(rng)
    image = bpy.data.images.new(name, *alpha.shape[::-1], alpha=True, float_buffer=True)
    rgba = np.zeros((*alpha.shape, 4), dtype=np.float32)
    rgba[..., 3] = alpha
    image.pixels.foreach_set(rgba.ravel())
    image.pack()
    kind = rng.choice(["principled", "mix", "inverted"])
    material = blender_scenes.cutout_material(image, kind)
    texture = next(n for n in material.node_tree.nodes if n.bl_idname == "ShaderNodeTexImage")
    texture.extension = rng.choice(["REPEAT", "REPEAT", "EXTEND", "CLIP", "MIRROR"])
    texture.interpolation = rng.choice(["Linear", "Linear", "Linear", "Closest"])
    if rng.random() < 0.3:
        location = (rng.uniform(-0.5, 0.5), rng.uniform(-0.5, 0.5), 0.0)
        rotation = (0.0, 0.0, rng.uniform(-math.pi, math.pi))
        scale = (rng.uniform(0.5, 2.0), rng.uniform(0.5, 2.0), 1.0)
        kind = rng.choice(["POINT", "TEXTURE"])
        blender_scenes.map_texture(material, texture, [(kind, location, rotation, scale)])
    return material


def add_cut_cards(
    rng: random.Random, scene: bpy.types.Scene, centre: np.ndarray, half: np.ndarray
) -> int:
    """One to three black cards over the fog box, tilted, cut by random alphas; returns
    how many."""
    count = rng.randint(1, 3)
    for index in range(count):
        side = rng.uniform(1.0, 4.0)
        at = centre + half * np.array(
            [rng.uniform(-0.8, 0.8), rng.uniform(-0.8, 0.8), rng.uniform(0.5, 1.4)]
        )
        tilt, yaw = rng.uniform(-0.6, 0.6), rng.uniform(0, math.pi)
        turn = np.array(
            [[math.cos(yaw), -math.sin(yaw), 0], [math.sin(yaw), math.cos(yaw), 0], [0, 0, 1]]
        ) @ np.array(
            [[1, 0, 0], [0, math.cos(tilt), -math.sin(tilt)], [0, math.sin(tilt), math.cos(tilt)]]
        )
        square = np.array([(-1, -1, 0), (1, -1, 0), (1, 1, 0), (-1, 1, 0)]) * side
        corners = [tuple(at + turn @ corner) for corner in square]
        material = random_cutout(rng, f"cut_{index}")
        start = rng.choice([0.0, rng.uniform(-1.0, 0.0)])
        repeats = rng.uniform(1, 3)
        blender_scenes.add_card(scene, f"card_{index}", corners, material, repeats, start)
    return count


def add_strands(
    rng: random.Random, scene: bpy.types.Scene, centre: np.ndarray, half: np.ndarray
) -> int:
    """A hair curves object of 10 to 40 black strands over the fog box, each a wavy line
    of 6 to 12 points in a random direction, of radius 2 to 15 cm; returns how many."""
    count = rng.randint(10, 40)
    strands = []
    for _ in range(count):
        start = centre + half * np.array(
            [rng.uniform(-1, 1), rng.uniform(-1, 1), rng.uniform(0.3, 1.3)]
        )
        heading = rng.uniform(0, 2 * math.pi)
        direction = np.array([math.cos(heading), math.sin(heading), rng.uniform(-0.3, 0.3)])
        t = np.linspace(0.0, rng.uniform(2, 8), rng.randint(6, 12))
        wave = 0.3 * np.sin(t * rng.uniform(0.5, 2.0))[:, None] * np.array([0.0, 0.0, 1.0])
        strands.append(start + t[:, None] * direction + wave)
    black = blender_scenes.black_material(0.0)
    blender_scenes.add_hair(scene, "strands", strands, rng.uniform(0.02, 0.15), black)
    return count


def add_point_cloud(
    rng: random.Random,
    scene: bpy.types.Scene,
    centre: np.ndarray,
    half: np.ndarray,
    as_object: bool = False,
) -> int:
    """A point cloud of 20 to 300 black points over and in the fog box (a geometry-nodes
    Mesh to Points, or a Point Cloud object's own data where `as_object`), of radii from
    2 cm up to 5 to 50 cm; returns how many."""
    count = rng.randint(20, 300)
    spread = np.array([1.2, 1.2, 0.8])
    lift = np.array([0.0, 0.0, 0.5])
    centres = [
        centre + half * (lift + spread * np.array([rng.uniform(-1, 1) for _ in range(3)]))
        for _ in range(count)
    ]
    largest = rng.uniform(0.05, 0.5)
    radii = [rng.uniform(0.02, largest) for _ in range(count)]
    black = blender_scenes.black_material(0.0)
    add = blender_scenes.add_point_cloud if as_object else blender_scenes.add_points
    add(scene, "points", centres, radii, black)
    return count


def add_curve_shapes(
    rng: random.Random, scene: bpy.types.Scene, centre: np.ndarray, half: np.ndarray
) -> int:
    """One to three black shapes over and in the fog box that are not meshes: bevelled
    Bezier circles, extruded text, NURBS spheres, each at a random place, size and
    rotation; returns how many."""
    count = rng.randint(1, 3)
    black = blender_scenes.black_material(0.0)
    for _ in range(count):
        location = centre + half * np.array(
            [rng.uniform(-1, 1), rng.uniform(-1, 1), rng.uniform(0.2, 1.3)]
        )
        kind = rng.choice(["ring", "text", "surface"])
        if kind == "ring":
            bpy.ops.curve.primitive_bezier_circle_add(radius=rng.uniform(0.5, 2.0))
            bpy.context.active_object.data.bevel_depth = rng.uniform(0.05, 0.3)
        elif kind == "text":
            bpy.ops.object.text_add()
            text = bpy.context.active_object.data
            text.body, text.size, text.extrude = (
                "SHAFTS",
                rng.uniform(1, 2.5),
                rng.uniform(0.05, 0.2),
            )
        else:
            bpy.ops.surface.primitive_nurbs_surface_sphere_add(radius=rng.uniform(0.3, 1.2))
        shape = bpy.context.active_object
        shape.location = location
        shape.rotation_euler = [rng.uniform(-math.pi, math.pi) for _ in range(3)]
        shape.data.materials.append(black)
    return count


def add_fur(
    rng: random.Random, scene: bpy.types.Scene, centre: np.ndarray, half: np.ndarray
) -> int:
    """A legacy particle-hair emitter over or in the fog box: a tilted quad of 1 to 4 m a
    side growing 50 to 400 black hairs of 0.3 to 2 m, of root radius 1 to 5 cm, tapering
    or not (the emitter itself does not render); returns how many hairs."""
    count = rng.randint(50, 400)
    side = rng.uniform(1.0, 4.0) / 2
    middle = centre + half * np.array([rng.uniform(-1, 1), rng.uniform(-1, 1), rng.uniform(0, 1)])
    tilt = rng.uniform(-0.6, 0.6)
    corners = [
        middle + np.array([dx * side, dy * side, tilt * dx * side])
        for dx, dy in ((-1, -1), (1, -1), (1, 1), (-1, 1))
    ]
    emitter = blender_scenes.add_particle_hair(
        scene,
        "fur",
        [tuple(corner) for corner in corners],
        count,
        rng.uniform(0.3, 2.0),
        radius_scale=rng.uniform(0.02, 0.1),
        tip_radius=rng.choice([0.0, 1.0]),
        material=blender_scenes.black_material(0.0),
    )
    emitter.name = "fur"
    return count


def add_walls(
    rng: random.Random, scene: bpy.types.Scene, centre: np.ndarray, half: np.ndarray
) -> int:
    """One or two black walls or slabs over and in the fog box, each with one to three
    windows a Boolean modifier cuts (its cutters hidden), so that the faces around the
    windows are concave n-gons; returns how many windows."""
    windows = 0
    black = blender_scenes.black_material(0.0)
    for index in range(rng.randint(1, 2)):
        at = centre + half * np.array(
            [rng.uniform(-0.8, 0.8), rng.uniform(-0.8, 0.8), rng.uniform(0.3, 1.3)]
        )
        size = np.array([rng.uniform(2.0, 6.0), rng.uniform(2.0, 6.0), rng.uniform(0.1, 0.4)])
        turn = (rng.uniform(-0.5, 0.5), rng.choice([0.0, math.pi / 2, rng.uniform(0, 1.5)]), 0.0)
        bpy.ops.mesh.primitive_cube_add(size=1.0, location=tuple(at), rotation=turn)
        wall = bpy.context.active_object
        wall.name, wall.scale = f"wall_{index}", tuple(size)
        wall.data.materials.append(black)
        for hole in range(rng.randint(1, 3)):
            # Windows within the wall's face, through its thickness, in its own frame.
            extent = np.array([rng.uniform(0.15, 0.35), rng.uniform(0.15, 0.35), 3.0]) * size
            offset = np.array([rng.uniform(-0.25, 0.25), rng.uniform(-0.25, 0.25), 0.0]) * size
            placed = at + np.array(Euler(turn).to_matrix()) @ offset
            bpy.ops.mesh.primitive_cube_add(size=1.0, location=tuple(placed), rotation=turn)
            cutter = bpy.context.active_object
            cutter.name, cutter.scale = f"wall_{index}_window_{hole}", tuple(extent)
            cutter.hide_render, cutter.display_type = True, "BOUNDS"
            cutter.hide_set(True)
            window = wall.modifiers.new(f"window_{hole}", "BOOLEAN")
            window.object, window.operation = cutter, "DIFFERENCE"
            windows += 1
    return windows


def add_subdivided(
    rng: random.Random,
    scene: bpy.types.Scene,
    centre: np.ndarray,
    half: np.ndarray,
    cut: random.Random | None = None,
) -> int:
    """One to three black meshes over and in the fog box under a Subdivision Surface
    modifier (a cube, a cylinder of 5 to 9 sides, an icosphere or an open grid; render
    levels 1 to 3, either boundary rule, the limit surface on or off), some with creased
    edges and vertices; returns how many. With `cut`, most are cut by a random alpha
    through their UV maps, under a random *UV Smooth* (drawn from `cut`, so that the
    meshes are the same)."""
    count = rng.randint(1, 3)
    black = blender_scenes.black_material(0.0)
    for index in range(count):
        location = centre + half * np.array(
            [rng.uniform(-1, 1), rng.uniform(-1, 1), rng.uniform(0.2, 1.3)]
        )
        size = rng.uniform(0.5, 2.0)
        kind = rng.choice(["cube", "cylinder", "icosphere", "grid"])
        if kind == "cube":
            bpy.ops.mesh.primitive_cube_add(size=size)
        elif kind == "cylinder":
            bpy.ops.mesh.primitive_cylinder_add(vertices=rng.randint(5, 9), radius=size / 2)
        elif kind == "icosphere":
            bpy.ops.mesh.primitive_ico_sphere_add(subdivisions=1, radius=size / 2)
        else:
            bpy.ops.mesh.primitive_grid_add(x_subdivisions=4, y_subdivisions=3, size=size)
        shape = bpy.context.active_object
        shape.location = location
        shape.rotation_euler = [rng.uniform(-math.pi, math.pi) for _ in range(3)]
        mesh = shape.data
        if rng.random() < 0.5:
            creases = mesh.attributes.new("crease_edge", "FLOAT", "EDGE")
            for _ in range(rng.randint(1, 4)):
                creases.data[rng.randrange(len(mesh.edges))].value = rng.choice([1.0, rng.random()])
        if rng.random() < 0.3:
            corners = mesh.attributes.new("crease_vert", "FLOAT", "POINT")
            corners.data[rng.randrange(len(mesh.vertices))].value = rng.choice([1.0, rng.random()])
        modifier = shape.modifiers.new("Subdivision", "SUBSURF")
        modifier.render_levels = rng.randint(1, 3)
        modifier.boundary_smooth = rng.choice(["ALL", "PRESERVE_CORNERS"])
        modifier.use_limit_surface = rng.random() < 0.8
        if cut is not None and cut.random() < 0.7:
            mesh.materials.append(random_cutout(cut, f"subdivided_cut_{index}"))
            modifier.uv_smooth = cut.choice(
                ["PRESERVE_BOUNDARIES", "PRESERVE_BOUNDARIES", "NONE", "PRESERVE_CORNERS",
                 "PRESERVE_CORNERS_AND_JUNCTIONS", "PRESERVE_CORNERS_JUNCTIONS_AND_CONCAVE",
                 "SMOOTH_ALL"]
            )  # fmt: skip
        else:
            mesh.materials.append(black)
    return count


def build_case(
    rng: random.Random,
    width: int,
    height: int,
    samples: int,
    tinted: bool,
    cutouts: bool,
    hair: bool = False,
    points: bool = False,
    closures: bool = False,
    disc: bool = False,
    grouping: random.Random | None = None,
    point_objects: bool = False,
    shapes: random.Random | None = None,
    subdivided: random.Random | None = None,
    fur: random.Random | None = None,
    subdivided_cut: random.Random | None = None,
    walls: random.Random | None = None,
) -> tuple[bpy.types.Scene, bpy.types.Object, str]:
    """A random scene (see the module's doc); returns it, its sun and a one-line summary.
    With `grouping`, a generator of its own, its materials are rebuilt inside node groups
    (`blender_scenes.wrap_in_group`) after the scene is drawn, so that the scene is the
    one drawn without."""
    blender_scenes.reset()
    scene = bpy.context.scene
    blender_scenes.setup_cycles(scene, width=width, height=height, samples=samples)
    # The layers are written unfiltered; a filter this narrow is none.
    scene.cycles.filter_width = 0.01
    around = np.array([rng.uniform(-5, 5), rng.uniform(-5, 5), 0.0])
    black = blender_scenes.black_material(0.0)
    for mesh in random_geometry(rng, around):
        blender_scenes.add_mesh(
            scene, mesh["name"], mesh["positions"], mesh["triangles"], material=black
        )
    centre = around + np.array([rng.uniform(-3, 3), rng.uniform(-3, 3), rng.uniform(1.5, 4)])
    half = np.array([rng.uniform(2, 8), rng.uniform(2, 8), rng.uniform(1.5, 5)])
    yaw = rng.uniform(0, math.pi)
    cos, sin = math.cos(yaw), math.sin(yaw)
    world_from_cube = np.eye(4)
    world_from_cube[:3, :3] = np.array([[cos, -sin, 0], [sin, cos, 0], [0, 0, 1]]) @ np.diag(half)
    world_from_cube[:3, 3] = centre
    material, fog_label = random_fog(rng, tinted, closures)
    blender_scenes.add_fog_box(scene, world_from_cube, material)

    elevation, azimuth = math.radians(rng.uniform(10, 85)), rng.uniform(0, 2 * math.pi)
    travel = -np.array(
        [
            math.cos(elevation) * math.cos(azimuth),
            math.cos(elevation) * math.sin(azimuth),
            math.sin(elevation),
        ]
    )
    sun = blender_scenes.add_sun(scene, travel, strength=3.0, enabled=False)
    labels = [fog_label, f"sun {math.degrees(elevation):.0f}°"]
    if disc:
        sun.data.angle = math.radians(rng.uniform(1.0, 10.0))
        labels.append(f"disc {math.degrees(sun.data.angle):.1f}°")
    if cutouts:
        labels.append(f"{add_cut_cards(rng, scene, centre, half)} cut cards")
    if hair:
        labels.append(f"{add_strands(rng, scene, centre, half)} strands")
    if points:
        labels.append(f"{add_point_cloud(rng, scene, centre, half, point_objects)} points")
    if shapes is not None:
        labels.append(f"{add_curve_shapes(shapes, scene, centre, half)} curve shapes")
    if subdivided is not None:
        cut = subdivided_cut if cutouts else None
        labels.append(f"{add_subdivided(subdivided, scene, centre, half, cut)} subdivided")
    if fur is not None:
        labels.append(f"{add_fur(fur, scene, centre, half)} hairs")
    if walls is not None:
        labels.append(f"{add_walls(walls, scene, centre, half)} windows")
    if rng.random() < 0.4:
        sun.data.color = (rng.uniform(0.5, 1), rng.uniform(0.5, 1), rng.uniform(0.5, 1))
        labels.append("coloured")
    if rng.random() < 0.2:
        sun.data.use_temperature, sun.data.temperature = True, rng.uniform(3000, 9000)
        sun.data.exposure = rng.uniform(-1, 1)
        labels.append("temperature")
    settings = sun.data.crepuscular
    settings.method, settings.steps, settings.shadow_map_size = "reference", 2048, 2048
    settings.edge_samples, settings.max_distance = 1, 200.0

    inside = rng.random() < 0.15
    if inside:
        eye = centre + half * np.array([rng.uniform(-0.5, 0.5), rng.uniform(-0.5, 0.5), -0.2])
        eye[2] = max(eye[2], 0.5)
        heading = rng.uniform(0, 2 * math.pi)
        target = eye + np.array([math.cos(heading), math.sin(heading), rng.uniform(-0.2, 0.6)])
        labels.append("inside")
    elif rng.random() < 0.25:
        # Past the box towards the sun: the epipole on screen, or close to it.
        towards = np.array([travel[0], travel[1], 0.0]) / math.hypot(travel[0], travel[1])
        eye = centre + rng.uniform(1.5, 3.0) * np.linalg.norm(half) * towards
        eye[2] = rng.uniform(0.3, 2.0)
        target = centre + np.array([0.0, 0.0, rng.uniform(0.0, 3.0)])
        labels.append("sunward")
    else:
        distance = rng.uniform(1.2, 3.0) * np.linalg.norm(half)
        heading, pitch = rng.uniform(0, 2 * math.pi), math.radians(rng.uniform(-5, 45))
        eye = centre + distance * np.array(
            [
                math.cos(pitch) * math.cos(heading),
                math.cos(pitch) * math.sin(heading),
                math.sin(pitch),
            ]
        )
        eye[2] = max(eye[2], 0.3)
        target = centre + np.array([rng.gauss(0, 1), rng.gauss(0, 1), rng.gauss(0, 0.5)])
    camera = blender_scenes.add_camera(
        scene, blender_scenes.look_at(eye, target), lens=rng.uniform(20, 70)
    )
    camera.data.clip_end = 200.0
    if rng.random() < 0.3:
        camera.data.shift_x, camera.data.shift_y = rng.uniform(-0.3, 0.3), rng.uniform(-0.3, 0.3)
        labels.append("shift")
    if rng.random() < 0.3:
        camera.data.sensor_fit = rng.choice(["VERTICAL", "HORIZONTAL"])
        labels.append(f"fit {camera.data.sensor_fit.lower()}")
    if rng.random() < 0.2:
        camera.data.type = "ORTHO"
        camera.data.ortho_scale = rng.uniform(1.0, 2.5) * 2 * float(np.max(half))
        labels.append("orthographic")
    if grouping is not None:
        fog_and_cards = [material] + [
            slot.material
            for obj in scene.objects
            if obj.name.startswith("card_")
            for slot in obj.material_slots
        ]
        for wrapped in fog_and_cards:
            blender_scenes.wrap_in_group(wrapped, grouping)
        labels.append("grouped")
    return scene, sun, " ".join(labels)


def rgb(path: Path, prefix: str = "") -> np.ndarray:
    channels = crepuscular.read_exr(path)
    return np.stack([channels[f"{prefix}{c}"] for c in "RGB"], axis=-1).astype(np.float64)


def block_means(image: np.ndarray, side: int = 4) -> np.ndarray:
    height, width = image.shape[0] // side * side, image.shape[1] // side * side
    blocks = image[:height, :width].reshape(height // side, side, width // side, side, -1)
    return blocks.mean(axis=(1, 3))


def scene_description(inputs: dict, out: Path) -> dict:
    """The extension's frame inputs (`export.frame_inputs(...).kwargs`) as a scene
    description for `crepuscular render --scene`: a mesh per object id, alpha mask and
    visibility, placed at the inputs' origin, each mask's alpha written beside it as an
    EXR."""
    world_from_object = np.eye(4)
    world_from_object[:3, 3] = inputs["origin"]
    triangle_masks = inputs.get("triangle_masks")
    if triangle_masks is None:
        triangle_masks = np.full(len(inputs["triangles"]), -1)
    for index, mask in enumerate(inputs.get("masks", [])):
        # Files store rows from the top; the mask's run from v = 0, the bottom.
        alpha = np.ascontiguousarray(np.flipud(np.asarray(mask.alpha, dtype=np.float32)))
        zeros = np.zeros_like(alpha)
        planes = {"R": zeros, "G": zeros, "B": zeros, "A": alpha}
        crepuscular.write_exr_channels(out / f"mask_{index}.exr", planes)
    visibility = inputs.get("triangle_visibility")
    if visibility is None:
        visibility = np.full(len(inputs["triangles"]), 3)
    meshes = []
    keys = zip(inputs["object_ids"], triangle_masks, visibility, strict=True)
    for object_id, mask, flags in sorted(set(keys)):
        selected = (
            (inputs["object_ids"] == object_id) & (triangle_masks == mask) & (visibility == flags)
        )
        rows = inputs["triangles"][selected]
        used, triangles = np.unique(rows, return_inverse=True)
        mesh = {
            "name": f"object {object_id}" + (f" mask {mask}" if mask >= 0 else ""),
            "object_id": int(object_id),
            "world_from_object": world_from_object.T.flatten().tolist(),
            "positions": inputs["positions"][used].tolist(),
            "triangles": triangles.reshape(-1, 3).tolist(),
        }
        if not flags & crepuscular.BLOCKS_SUN:
            mesh["blocks_sun"] = False
        if not flags & crepuscular.SEEN_BY_CAMERA:
            mesh["seen_by_camera"] = False
        if mask >= 0:
            mesh["uvs"] = inputs["uvs"][used].tolist()
            alpha_mask = inputs["masks"][mask]
            mesh["alpha_mask"] = {
                "image": f"mask_{mask}.exr",
                "threshold": float(alpha_mask.threshold),
                "wrap": alpha_mask.wrap,
                "filter": alpha_mask.filter,
                "border": float(alpha_mask.border),
            }
        meshes.append(mesh)
    description = {
        "version": crepuscular.SCENE_VERSION,
        "camera": inputs["camera"],
        "sun": inputs["sun"],
        "medium": inputs["medium"],
        "render": inputs["settings"],
        "meshes": meshes,
    }
    if inputs["style"]:
        description["style"] = inputs["style"]
    return description


def render_case(scene: bpy.types.Scene, sun: bpy.types.Object, out: Path) -> dict[str, Path]:
    """Cycles twice (seeds 1 and 2), then the layers of each of `METHODS`, and the
    reference's inputs as `scene.json`."""
    paths = {}
    for seed in (1, 2):
        scene.cycles.seed = seed
        paths[f"cycles {seed}"] = out / f"cycles_{seed}.exr"
        scene.render.filepath = str(paths[f"cycles {seed}"])
        bpy.ops.render.render(write_still=True)
    settings = sun.data.crepuscular
    settings.enabled = True
    default = settings.bl_rna.properties["method"].default
    for method in METHODS:
        settings.method = default if method == "default" else method
        paths[method] = out / f"{method}.exr"
        result = bpy.ops.crepuscular.render_layers(filepath=str(paths[method]))
        if result != {"FINISHED"}:
            raise RuntimeError(f"render_layers with '{settings.method}' returned {result}")
    settings.method = "reference"
    export = sys.modules[blender_scenes.ADDON_MODULE].export
    inputs = export.frame_inputs(scene, bpy.context.evaluated_depsgraph_get()).kwargs
    paths["scene"] = out / "scene.json"
    paths["scene"].write_text(json.dumps(scene_description(inputs, out)))
    return paths


def render_through_usd(scene: bpy.types.Scene, out: Path) -> Path:
    """The case exported with Blender's USD exporter and rendered by `crepuscular-usd` in a
    process of its own (it holds usd-core's bindings, Blender its own), in the whole frame
    where the render is cropped to a region, as the USD step renders a data window."""
    stage = out / "shot.usda"
    if bpy.ops.wm.usd_export(filepath=str(stage)) != {"FINISHED"}:
        raise RuntimeError("Blender's USD export failed")
    layers = out / "usd.exr"
    command = [sys.executable, "-m", "crepuscular_usd.cli", "render", str(stage), "--quiet"]
    done = subprocess.run(
        [*command, "--out", str(layers)], capture_output=True, text=True, check=False
    )
    if done.returncode != 0:
        raise RuntimeError(f"crepuscular-usd failed: {done.stderr.strip()}")
    return layers


def cropped_as_ours(scene: bpy.types.Scene, image: np.ndarray) -> np.ndarray:
    """`image`, a USD step's render of the whole frame, cropped to the extension's render
    region where the extension crops to it."""
    region = sys.modules[blender_scenes.ADDON_MODULE].export.render_region(scene)
    if region is None or not region.cropped:
        return image
    return image[region.y : region.y + region.height, region.x : region.x + region.width]


def usd_difference(scene: bpy.types.Scene, ours: Path, usd: Path) -> float:
    """The largest mean relative difference per layer between the extension's layers and
    the USD step's, these cropped to the extension's region where it crops."""
    mine, theirs = crepuscular.read_exr(ours), crepuscular.read_exr(usd)
    worst = 0.0
    for name in USD_LAYERS:
        plane = cropped_as_ours(scene, theirs[name])
        scale = float(np.abs(mine[name]).mean())
        if plane.shape != mine[name].shape:
            return math.inf
        difference = float(np.abs(mine[name] - plane).mean())
        worst = max(worst, difference / scale if scale > 0 else difference)
    return worst


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--cases", type=int, default=20)
    parser.add_argument("--width", type=int, default=160)
    parser.add_argument("--height", type=int, default=90)
    parser.add_argument("--samples", type=int, default=512, help="Cycles samples per pixel")
    parser.add_argument("--flag", type=float, default=2.0, help="percent error to flag")
    parser.add_argument("--tinted", action="store_true", help="coloured fog (see above)")
    parser.add_argument("--cutouts", action="store_true", help="cards cut by an image's alpha")
    parser.add_argument("--hair", action="store_true", help="hair strands over the box")
    parser.add_argument("--points", action="store_true", help="a point cloud over the box")
    parser.add_argument(
        "--closures", action="store_true", help="fog of several volume closures (see above)"
    )
    parser.add_argument("--disc", action="store_true", help="a sun disc of 1 to 10 degrees")
    parser.add_argument(
        "--grouped", action="store_true", help="materials rebuilt inside node groups (see above)"
    )
    parser.add_argument(
        "--anamorphic", action="store_true", help="non-square pixels, 1:2 to 2:1 (see above)"
    )
    parser.add_argument(
        "--region", action="store_true", help="a random render region, cropped or not"
    )
    parser.add_argument(
        "--usd", action="store_true", help="also through Blender's USD export and the USD step"
    )
    parser.add_argument(
        "--curves",
        action="store_true",
        help="bevelled curves, text and NURBS spheres over the box (see above)",
    )
    parser.add_argument(
        "--subdivided",
        action="store_true",
        help="meshes under a Subdivision Surface modifier over the box (see above)",
    )
    parser.add_argument(
        "--fur", action="store_true", help="a legacy particle-hair emitter over the box"
    )
    parser.add_argument(
        "--booleans", action="store_true", help="walls with windows a Boolean cuts (see above)"
    )
    parser.add_argument(
        "--shadowless", action="store_true", help="the sun's Cast Shadow off (see above)"
    )
    parser.add_argument("--out", type=Path, help="folder to keep each case's renders in")
    args = parser.parse_args()
    blender_scenes.install_addon()
    out_root = args.out or Path(tempfile.mkdtemp(prefix="crepuscular-cycles-views-out-"))
    flagged = black = 0
    for case in range(args.cases):
        # One generator per case, so that any case can be drawn again alone.
        rng = random.Random(f"{args.seed} {case}")
        scene, sun, summary = build_case(
            rng,
            args.width,
            args.height,
            args.samples,
            args.tinted,
            args.cutouts,
            args.hair,
            args.points,
            args.closures,
            args.disc,
            random.Random(f"{args.seed} {case} grouping") if args.grouped else None,
            # Through USD, half the clouds are Point Cloud objects, which Blender's
            # exporter writes itself, and half geometry nodes', which the hook adds.
            point_objects=args.usd and random.Random(f"{args.seed} {case} cloud").random() < 0.5,
            shapes=random.Random(f"{args.seed} {case} shapes") if args.curves else None,
            subdivided=(
                random.Random(f"{args.seed} {case} subdivided") if args.subdivided else None
            ),
            fur=random.Random(f"{args.seed} {case} fur") if args.fur else None,
            subdivided_cut=random.Random(f"{args.seed} {case} subdivided cut"),
            walls=random.Random(f"{args.seed} {case} walls") if args.booleans else None,
        )
        if args.anamorphic:
            aspect = random.Random(f"{args.seed} {case} pixels").uniform(0.5, 2.0)
            # Blender keeps each side of the aspect at 1 or more.
            scene.render.pixel_aspect_x = max(aspect, 1.0)
            scene.render.pixel_aspect_y = max(1.0 / aspect, 1.0)
            summary += f" pixels {aspect:.2f}:1"
        if args.region:
            draw = random.Random(f"{args.seed} {case} region")
            render = scene.render
            render.use_border, render.use_crop_to_border = True, draw.random() < 0.5
            # At least a fifth of each side, so that it holds blocks to compare.
            for axis in "xy":
                low = draw.uniform(0.0, 0.8)
                setattr(render, f"border_min_{axis}", low)
                setattr(render, f"border_max_{axis}", draw.uniform(low + 0.2, 1.0))
            summary += " region" + (" cropped" if render.use_crop_to_border else "")
        if args.shadowless:
            sun.data.use_shadow = False
            summary += " shadowless"
        out = out_root / f"case_{args.seed}_{case}"
        out.mkdir(parents=True, exist_ok=True)
        started = time.perf_counter()
        try:
            paths = render_case(scene, sun, out)
            if args.usd:
                paths["usd"] = render_through_usd(scene, out)
        except RuntimeError as error:
            print(f"{case:3} {summary} | error: {error}", flush=True)
            continue
        seconds = time.perf_counter() - started
        first, second = rgb(paths["cycles 1"]), rgb(paths["cycles 2"])
        cycles = 0.5 * (first + second)
        mean = cycles.mean()
        # A view that sees no lit fog can still catch a stray path's 1e-10.
        if mean <= 1e-8:
            black += 1
            print(f"{case:3} {summary} | black: the view sees no lit fog", flush=True)
            continue
        noise = 50 * np.abs(block_means(first) - block_means(second)).mean() / mean
        columns = [f"Cycles mean {mean:.3g} noise {noise:.2f}%"]
        worst = 0.0
        for method in METHODS:
            ours = rgb(paths[method], "volume.")
            error = 100 * np.abs(block_means(ours) - block_means(cycles)).mean() / mean
            worst = max(worst, error)
            columns.append(f"{method} mean {ours.mean() / mean:.3f} error {error:5.2f}%")
        usd_off = 0.0
        if args.usd:
            through_usd = cropped_as_ours(scene, rgb(paths["usd"], "volume."))
            error = 100 * np.abs(block_means(through_usd) - block_means(cycles)).mean() / mean
            worst = max(worst, error)
            usd_off = usd_difference(scene, paths["reference"], paths["usd"])
            columns.append(f"usd error {error:5.2f}% usd vs ours {usd_off:.1e}")
        flag = worst > args.flag or usd_off > USD_FLAG
        flagged += flag
        print(
            f"{case:3} {summary} | {' | '.join(columns)} ({seconds:.0f} s)"
            + ("  <<<" if flag else ""),
            flush=True,
        )
    print(f"{flagged} of {args.cases - black} cases above {args.flag}% ({black} black)")
    print(f"renders and each case's scene.json (for `crepuscular render --scene`) in {out_root}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
