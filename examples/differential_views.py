"""Fast methods against the reference on random views: a search for failure cases.

Each case draws a built-in scene, a sun, a camera (perspective or orthographic, aimed at
the subject, into the sun or away from it), a medium (thin to dense, sometimes a box),
render settings (reach, near-plane correction, downsampling, supersampling) and a style,
renders it with `reference`, `minmax` and `prefiltered` through the public API, and prints
each fast method's mean absolute error over the mean reference radiance. Cases above
`--flag` percent are written out as scene JSON for `crepuscular render --scene`.

Nearly black images inflate the relative error: look at the mean radiance printed beside
it before chasing one. Against a black reference each method's mean is printed instead,
and a case is flagged when one leaves more than `BLACK_LEAK` there.

    .venv/bin/python examples/differential_views.py --seed 2 --cases 60 --out /tmp/cases

`--geometry random` replaces each case's meshes with a scene of its own drawn from the same
seed: a ground, walls with windows, pillars, a slatted roof and scattered leaves, at
random sizes and places around the subject, as scenes the built-in ones do not resemble.

`--exact-ray-ends on` (or `off`) renders the same cases with prefiltering's exact ray ends
everywhere (or nowhere); by default they are on in box media only. `--box-only` puts
every case's medium in a box, to compare those two on box media alone. `--below-horizon`
turns every case's sun below the horizon (its light travelling upward, as a sun lamp
pointed up in Blender sends it), the cases otherwise as drawn. `--slices 4096` renders
every case with that many epipolar slices rather than the automatic count.
`--anamorphic` renders each case through non-square pixels (1:2 to 2:1, the width scaled
to keep the view's shape), and `--window` renders a random window of each case's frame, a
render region: both draw from generators of their own, so that seeds keep their cases.
`--undimmed` renders every case with sunlight that a box medium does not attenuate (a sun
that casts no shadows, its casters kept), the same cases otherwise.
"""

from __future__ import annotations

import argparse
import copy
import json
import math
import random
import sys
from pathlib import Path

import numpy as np

import crepuscular

STYLES: list[dict | None] = [
    None,
    {"version": 1, "closing": {"operation": "close", "kernel": "disk", "radius": 0.6}},
    {"version": 1, "silhouette": {"operation": "close", "length": 0.4}},
    {"version": 1, "silhouette": {"operation": "dilate", "length": 0.3}},
    {
        "version": 1,
        "holes": {
            "frequency": 0.03,
            "persistence": 0.5,
            "octaves": 3,
            "threshold": 0.5,
            "grid_size": 64,
            "seed": 3,
            "speed": 0.0,
            "warp": 0.3,
            "objects": [],
        },
    },
]


UP = np.array([0.0, 0.0, 1.0])
IDENTITY = [1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0]


# A box's faces as corner indices (bit 0: +x, bit 1: +y, bit 2: +z), each in order around it.
BOX_FACES = ((0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3))


class MeshDraft:
    """Positions and triangles of one mesh, built box by box and quad by quad."""

    def __init__(self) -> None:
        self.positions: list[list[float]] = []
        self.triangles: list[list[int]] = []

    def quad(self, corners: np.ndarray) -> None:
        """Two triangles over four corners given in order around the quad."""
        base = len(self.positions)
        self.positions.extend(corners.tolist())
        self.triangles.extend([[base, base + 1, base + 2], [base, base + 2, base + 3]])

    def box(self, centre: np.ndarray, half: np.ndarray, yaw: float) -> None:
        """A closed box of half extents `half`, turned by `yaw` about the vertical."""
        c, s = math.cos(yaw), math.sin(yaw)
        rotation = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        signs = np.array([[x, y, z] for z in (-1, 1) for y in (-1, 1) for x in (-1, 1)])
        corners = centre + (signs * half) @ rotation.T
        base = len(self.positions)
        self.positions.extend(corners.tolist())
        for face in BOX_FACES:
            a, b, c_, d = (base + k for k in face)
            self.triangles.extend([[a, b, c_], [a, c_, d]])

    def mesh(self, name: str, object_id: int) -> dict:
        return {
            "name": name,
            "object_id": object_id,
            "world_from_object": list(IDENTITY),
            "positions": self.positions,
            "triangles": self.triangles,
        }


def random_geometry(rng: random.Random, around: np.ndarray, ground: bool = True) -> list[dict]:
    """Meshes unlike the built-in scenes', around the point `around` that the camera aims
    near: a ground (sometimes none, never without `ground`), a wall with a grid of windows,
    pillars, a slatted roof, leaves."""
    meshes = []
    around = np.array([around[0], around[1], 0.0])
    # Drawn either way, so that the rest is the same with or without `ground`.
    has_ground, extent = rng.random() < 0.8, rng.uniform(15, 60)
    if has_ground and ground:
        plane = MeshDraft()
        corners = [[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]]
        plane.quad(around + extent * np.array(corners, float))
        meshes.append(plane.mesh("ground", 1))
    wall = MeshDraft()
    yaw = rng.uniform(0, math.pi)
    along = np.array([math.cos(yaw), math.sin(yaw), 0.0])
    across = np.array([-math.sin(yaw), math.cos(yaw), 0.0])
    offset = around + rng.uniform(-4, 4) * across
    length, height = rng.uniform(4, 14), rng.uniform(2, 7)
    columns, rows = rng.randint(2, 9), rng.randint(1, 4)
    opening = rng.uniform(0.2, 0.7)
    thickness = rng.uniform(0.05, 0.4)
    cell_w, cell_h = length / columns, height / rows
    # The solid parts: a frame around each window, as boxes between the openings.
    post, rail = cell_w * (1 - opening) / 2, max(cell_h * (1 - opening) / 2, 0.02)
    for k in range(columns + 1):
        centre = offset + along * (k * cell_w - length / 2) + UP * height / 2
        wall.box(centre, np.array([post, thickness, height / 2]), yaw)
    for r in range(rows + 1):
        wall.box(offset + UP * r * cell_h, np.array([length / 2, thickness, rail]), yaw)
    meshes.append(wall.mesh("wall", 2))
    pillars = MeshDraft()
    for _ in range(rng.randint(0, 8)):
        centre = around + np.array([rng.uniform(-8, 8), rng.uniform(-8, 8), 0.0])
        radius, tall = rng.uniform(0.05, 0.6), rng.uniform(1, 9)
        half = np.array([radius, radius, tall / 2])
        pillars.box(centre + UP * tall / 2, half, rng.uniform(0, math.pi))
    if pillars.triangles:
        meshes.append(pillars.mesh("pillars", 3))
    if rng.random() < 0.6:
        roof = MeshDraft()
        slats, spacing = rng.randint(4, 30), rng.uniform(0.1, 1.0)
        width = spacing * rng.uniform(0.2, 0.8)
        z = rng.uniform(2.5, 8)
        span = rng.uniform(3, 12)
        roof_yaw = rng.uniform(0, math.pi)
        centre = around + np.array([rng.uniform(-3, 3), rng.uniform(-3, 3), z])
        direction = np.array([math.cos(roof_yaw), math.sin(roof_yaw), 0.0])
        for k in range(slats):
            shift = (k - (slats - 1) / 2) * spacing
            roof.box(centre + direction * shift, np.array([width / 2, span / 2, 0.03]), roof_yaw)
        meshes.append(roof.mesh("roof", 4))
    if rng.random() < 0.5:
        leaves = MeshDraft()
        crown = around + np.array([rng.uniform(-5, 5), rng.uniform(-5, 5), rng.uniform(2, 6)])
        spread, size = rng.uniform(0.8, 3.0), rng.uniform(0.05, 0.4)
        for _ in range(rng.randint(50, 600)):
            centre = crown + np.array([rng.gauss(0, spread) for _ in range(3)])
            normal = np.array([rng.gauss(0, 1) for _ in range(3)])
            normal /= np.linalg.norm(normal)
            tangent = np.cross(normal, UP if abs(normal[2]) < 0.9 else [1.0, 0.0, 0.0])
            tangent /= np.linalg.norm(tangent)
            bitangent = np.cross(normal, tangent)
            corners = [-tangent - bitangent, tangent - bitangent, tangent + bitangent]
            leaves.quad(centre + size * np.array([*corners, bitangent - tangent]))
        meshes.append(leaves.mesh("leaves", 5))
    return meshes


def look_at(eye: np.ndarray, target: np.ndarray) -> list[float]:
    """A column-major world-from-camera matrix looking from `eye` at `target`."""
    forward = target - eye
    forward /= np.linalg.norm(forward)
    up = np.array([0.0, 0.0, 1.0]) if abs(forward[2]) < 0.99 else np.array([0.0, 1.0, 0.0])
    right = np.cross(forward, up)
    right /= np.linalg.norm(right)
    matrix = np.eye(4)
    matrix[:3, 0] = right
    matrix[:3, 1] = np.cross(right, forward)
    matrix[:3, 2] = -forward
    matrix[:3, 3] = eye
    return matrix.T.ravel().tolist()


# Mean radiance below which a reference counts as black, and the mean a method may leave
# there before the case is flagged (prefiltering's ringing floor is of the order of 1e-4).
BLACK = 1e-9
BLACK_LEAK = 1e-3


def random_case(
    rng: random.Random,
    width: int,
    height: int,
    box_only: bool = False,
    below_horizon: bool = False,
    geometry: random.Random | None = None,
) -> tuple[str, dict]:
    name = rng.choice(list(crepuscular.builtin_scene_names()))
    scene = crepuscular.builtin_scene(name)
    # Turned by sign, not drawn apart, so that the cases are the same either way.
    elevation = math.radians(rng.uniform(8, 89)) * (-1 if below_horizon else 1)
    azimuth = rng.uniform(0, 2 * math.pi)
    scene["sun"]["direction"] = [
        -math.cos(elevation) * math.cos(azimuth),
        -math.cos(elevation) * math.sin(azimuth),
        -math.sin(elevation),
    ]
    towards_sun = -np.array(scene["sun"]["direction"])
    eye = np.array([rng.uniform(-14, 14), rng.uniform(-14, 14), rng.uniform(0.3, 8)])
    jitter = np.array([rng.gauss(0, 1.5) for _ in range(3)])
    aim = rng.random()
    if aim < 0.3:
        target = eye + 5 * towards_sun + jitter
    elif aim < 0.45:
        target = eye - 5 * towards_sun + jitter
    else:
        target = np.array([rng.uniform(-3, 3), rng.uniform(-3, 3), rng.uniform(0, 3)])
    if geometry is not None:
        # Drawn from a generator of their own, so that the views are the same cases' views
        # with the built-in meshes.
        # Light from below the horizon would reach nothing above a ground but the film
        # within the shadow bias of it.
        scene["meshes"] = random_geometry(geometry, target, ground=not below_horizon)
        name = "random"
    camera = scene["camera"]
    camera["world_from_camera"] = look_at(eye, target)
    camera["width"], camera["height"] = width, height
    if rng.random() < 0.2:
        camera["projection"] = {
            "kind": "orthographic",
            "ortho_scale": rng.uniform(5, 25),
            "sensor_fit": "auto",
            "shift_x": 0.0,
            "shift_y": 0.0,
        }
    else:
        camera["projection"]["focal_length"] = rng.choice([18.0, 35.0, 50.0, 85.0])
    medium = scene["medium"]
    medium["extinction"] = rng.choice([0.01, 0.05, 0.2, 0.6])
    medium["anisotropy"] = rng.uniform(-0.5, 0.8)
    # The draw comes first, so that cases drawn with a box are the same with `box_only`.
    if rng.random() < 0.25 or box_only:
        # Around what the camera looks at, so that the box is in view: centred on the
        # scene's middle, five of seed 40's nine boxes lay outside the image.
        cx, cy, cz = (
            target[0] + rng.uniform(-3, 3),
            target[1] + rng.uniform(-3, 3),
            rng.uniform(1, 4),
        )
        sx, sy, sz = rng.uniform(3, 12), rng.uniform(3, 12), rng.uniform(2, 6)
        medium["extent"] = {
            "kind": "box",
            "world_from_cube": [sx, 0, 0, 0, 0, sy, 0, 0, 0, 0, sz, 0, cx, cy, cz, 1],
        }
    settings = scene["render"]
    settings["max_distance"] = rng.choice([70.0, 30.0, 12.0])
    settings["near_plane_correction"] = rng.random() < 0.7
    settings["steps"] = 4096
    resolution = rng.random()
    if resolution < 0.2:
        settings["downsample"] = 2
    elif resolution < 0.4:
        settings["supersampling"] = 2
    style = rng.choice(STYLES)
    if style is not None:
        scene["style"] = copy.deepcopy(style)
        if "holes" in style:
            # Holes in every object but the first (the ground), by the scene's own ids.
            ids = sorted({mesh["object_id"] for mesh in scene["meshes"]})
            scene["style"]["holes"]["objects"] = ids[1:] or ids
    return name, scene


def describe(name: str, scene: dict) -> str:
    style = scene.get("style")
    operators = [key for key in ("closing", "silhouette", "holes") if style and key in style]
    settings, medium = scene["render"], scene["medium"]
    elevation = math.degrees(math.asin(-scene["sun"]["direction"][2]))
    return (
        f"{name:<9} sun {elevation:2.0f}° {scene['camera']['projection']['kind']:<12} "
        f"extinction {medium['extinction']:<4} {medium['extent']['kind']:<9} "
        f"reach {settings['max_distance']:<4} 1/{settings.get('downsample', 1)} "
        f"ss {settings.get('supersampling', 1)} style {'+'.join(operators) or '-'}"
        # Prefiltering then also counts the fog before the near clip plane, which the
        # reference skips: in dense open media that alone is several percent.
        + ("" if settings.get("near_plane_correction", True) else " near plane uncorrected")
    )


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--cases", type=int, default=30)
    parser.add_argument("--width", type=int, default=192)
    parser.add_argument("--height", type=int, default=108)
    parser.add_argument("--flag", type=float, default=3.0, help="percent error to flag")
    parser.add_argument("--out", type=Path, help="folder for the flagged cases' scene JSON")
    parser.add_argument(
        "--exact-ray-ends",
        choices=("auto", "on", "off"),
        default="auto",
        help="prefiltering's exact ray ends (the same cases whichever): auto (in box media), "
        "on or off",
    )
    parser.add_argument(
        "--box-only",
        action="store_true",
        help="confine every case's medium to a box (the cases that draw one keep theirs)",
    )
    parser.add_argument(
        "--below-horizon",
        action="store_true",
        help="turn every case's sun below the horizon, its light travelling upward",
    )
    parser.add_argument(
        "--geometry",
        choices=("builtin", "random"),
        default="builtin",
        help="each case's meshes: a built-in scene's, or drawn at random (see above)",
    )
    parser.add_argument(
        "--slices",
        type=int,
        default=0,
        help="epipolar slices for the fast methods' rectified map in every case (0: automatic)",
    )
    parser.add_argument(
        "--anamorphic", action="store_true", help="non-square pixels, 1:2 to 2:1 (see above)"
    )
    parser.add_argument("--window", action="store_true", help="a random window of the frame")
    parser.add_argument(
        "--undimmed",
        action="store_true",
        help="sunlight not attenuated by a box medium (see above)",
    )
    args = parser.parse_args()
    rng = random.Random(args.seed)
    geometry = random.Random(f"{args.seed} geometry") if args.geometry == "random" else None
    if args.out is not None:
        args.out.mkdir(parents=True, exist_ok=True)
    flagged = 0
    for case in range(args.cases):
        name, scene = random_case(
            rng,
            args.width,
            args.height,
            args.box_only,
            args.below_horizon,
            geometry,
        )
        scene["render"]["exact_ray_ends"] = args.exact_ray_ends
        scene["render"]["epipolar_slices"] = args.slices
        camera = scene["camera"]
        if args.anamorphic:
            aspect = random.Random(f"{args.seed} {case} pixels").uniform(0.5, 2.0)
            camera["pixel_aspect"] = aspect
            camera["width"] = max(1, round(camera["width"] / aspect))
            name += f" pixels {aspect:.2f}:1"
        if args.undimmed:
            scene["sun"]["attenuated_by_medium"] = False
            name += " undimmed"
        if args.window:
            draw = random.Random(f"{args.seed} {case} window")
            x0, y0 = draw.randrange(camera["width"] // 2), draw.randrange(camera["height"] // 2)
            width = draw.randint(max(4, camera["width"] // 5), camera["width"] - x0)
            height = draw.randint(max(4, camera["height"] // 5), camera["height"] - y0)
            camera["window"] = {"x": x0, "y": y0, "width": width, "height": height}
            name += f" window {width}x{height}"
        volumes = {}
        try:
            for method in ("reference", "minmax", "prefiltered"):
                variant = copy.deepcopy(scene)
                variant["render"]["method"] = method
                volume = np.asarray(crepuscular.render(variant).volume)
                if not np.isfinite(volume).all():
                    print(f"{case:3} {describe(name, scene)} | {method}: non-finite values")
                volumes[method] = volume[..., :3].astype(np.float64)
        except crepuscular.CrepuscularError as error:
            print(f"{case:3} {describe(name, scene)} | error: {error}")
            continue
        reference = volumes["reference"]
        fast = ("minmax", "prefiltered")
        if reference.mean() < BLACK:
            # A relative error means nothing against a black reference: what the methods
            # leave there is shown as their mean instead.
            leaks = {method: volumes[method].mean() for method in fast}
            flag = max(leaks.values()) > BLACK_LEAK
            summary = (
                f"black reference: minmax mean {leaks['minmax']:.2g} "
                f"prefiltered mean {leaks['prefiltered']:.2g}"
            )
        else:
            total = reference.sum()
            errors = {
                method: 100 * np.abs(volumes[method] - reference).sum() / total for method in fast
            }
            flag = max(errors.values()) > args.flag
            summary = (
                f"minmax {errors['minmax']:6.2f}% prefiltered {errors['prefiltered']:6.2f}% "
                f"mean {reference.mean():.3g}"
            )
        flagged += flag
        print(
            f"{case:3} {describe(name, scene)} | {summary}" + ("  <<<" if flag else ""),
            flush=True,
        )
        if flag and args.out is not None:
            path = args.out / f"case_{args.seed}_{case}.json"
            path.write_text(json.dumps(scene))
    print(f"{flagged} of {args.cases} cases above {args.flag}%")
    return 0


if __name__ == "__main__":
    sys.exit(main())
