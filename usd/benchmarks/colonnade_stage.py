"""Authors a 100-frame colonnade stage and times `crepuscular-usd render` on it.

The stage holds the built-in `colonnade` scene's meshes (Z up, metres), its camera dollying
sideways over frames 1-100 and its sun turning slowly, both time-sampled on every frame, and
the `CrepuscularLightAPI` with the scene's medium and render settings. Usage:

    python usd/benchmarks/colonnade_stage.py --out-dir out/usd-bench [--method minmax]
        [--frames 1-100] [--width 1920 --height 1080]

It prints frames per second and the share of time spent reading USD versus rendering.
"""

from __future__ import annotations

import argparse
import io
import math
import sys
import time
from pathlib import Path

import numpy as np
from pxr import Gf, Usd, UsdGeom, UsdLux

import crepuscular
import crepuscular_usd
from crepuscular_usd.cli import main

FRAMES = 100


def author(path: Path, method: str) -> None:
    scene = crepuscular.builtin_scene("colonnade")
    stage = Usd.Stage.CreateNew(str(path))
    if not stage:
        raise SystemExit(f"cannot create {path}")
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    stage.SetStartTimeCode(1)
    stage.SetEndTimeCode(FRAMES)
    stage.SetTimeCodesPerSecond(24)
    world = UsdGeom.Xform.Define(stage, "/World")
    stage.SetDefaultPrim(world.GetPrim())
    for desc in scene["meshes"]:
        mesh = UsdGeom.Mesh.Define(stage, f"/World/{desc['name']}")
        matrix = np.reshape(desc["world_from_object"], (4, 4))  # column-major -> row vectors
        mesh.AddTransformOp().Set(Gf.Matrix4d(*matrix.ravel().tolist()))
        mesh.CreatePointsAttr([Gf.Vec3f(*p) for p in desc["positions"]])
        triangles = np.asarray(desc["triangles"])
        mesh.CreateFaceVertexCountsAttr([3] * len(triangles))
        mesh.CreateFaceVertexIndicesAttr(triangles.ravel().tolist())
        mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    cam = scene["camera"]
    camera = UsdGeom.Camera.Define(stage, "/World/Camera")
    camera.CreateFocalLengthAttr(cam["projection"]["focal_length"])
    sensor = cam["projection"]["sensor_width"]
    camera.CreateHorizontalApertureAttr(sensor)
    camera.CreateVerticalApertureAttr(sensor * cam["height"] / cam["width"])
    camera.CreateClippingRangeAttr(Gf.Vec2f(cam["clip_start"], cam["clip_end"]))
    camera_op = camera.AddTransformOp()
    base = np.reshape(cam["world_from_camera"], (4, 4))  # rows are the columns
    sun = scene["sun"]
    light = UsdLux.DistantLight.Define(stage, "/World/Sun")
    light.CreateIntensityAttr(sun["strength"])
    light.CreateColorAttr(Gf.Vec3f(*sun["color"]))
    light.CreateAngleAttr(math.degrees(sun["angular_diameter"]))
    light_op = light.AddTransformOp()
    travel = np.asarray(sun["direction"], dtype=np.float64)
    for frame in range(1, FRAMES + 1):
        t = (frame - 1) / (FRAMES - 1)
        moved = base.copy()
        moved[3, 0] += 1.0 * t  # dolly 1 m along x
        camera_op.Set(Gf.Matrix4d(*moved.ravel().tolist()), Usd.TimeCode(frame))
        angle = math.radians(10.0 * t)  # the sun turns 10 degrees about the vertical
        turn = np.array(
            [
                [math.cos(angle), -math.sin(angle), 0],
                [math.sin(angle), math.cos(angle), 0],
                [0, 0, 1],
            ]
        )
        rotation = Gf.Rotation(Gf.Vec3d(0, 0, -1), Gf.Vec3d(*(turn @ travel)))
        light_op.Set(Gf.Matrix4d().SetRotate(rotation), Usd.TimeCode(frame))
    crepuscular_usd.apply_schema(
        light.GetPrim(),
        overrides={
            "crepuscular:medium:extinction": scene["medium"]["extinction"],
            "crepuscular:medium:anisotropy": scene["medium"]["anisotropy"],
            "crepuscular:method": method,
            "crepuscular:maxDistance": scene["render"]["max_distance"],
            "crepuscular:shadowMapSize": scene["render"]["shadow_map_size"],
        },
    )
    if not stage.GetRootLayer().Save():
        raise SystemExit(f"cannot save {path}")


def run() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out-dir", default="out/usd-bench")
    parser.add_argument(
        "--method", default="minmax", choices=("reference", "minmax", "prefiltered")
    )
    parser.add_argument("--frames", default=f"1-{FRAMES}")
    parser.add_argument("--width", default="1920")
    parser.add_argument("--height", default="1080")
    args = parser.parse_args()
    out = Path(args.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    stage_path = out / "colonnade.usda"
    author(stage_path, args.method)
    err = io.StringIO()
    started = time.perf_counter()
    status = main(
        [
            "render",
            str(stage_path),
            "--camera",
            "/World/Camera",
            "--frames",
            args.frames,
            "--out",
            str(out / "shafts.####.exr"),
            "--out-layer",
            str(out / "shafts.usda"),
            "--width",
            args.width,
            "--height",
            args.height,
        ],
        stderr=err,
    )
    wall = time.perf_counter() - started
    summary = [line for line in err.getvalue().splitlines() if "frame(s) in" in line]
    if status != 0 or not summary:
        sys.stderr.write(err.getvalue())
        return status or 1
    # "... N frame(s) in T s: read USD R s, render C s, write W s (overlapping ...)"
    numbers = [float(word) for word in summary[0].replace(",", " ").split() if _is_float(word)]
    frames, total, read, render, write = numbers[:5]
    print(summary[0])
    print(
        f"{int(frames)} frames at {args.width}x{args.height} ({args.method}) in {wall:.1f} s: "
        f"{frames / wall:.3f} fps; of the frame loop's {total:.1f} s, reading USD "
        f"{100 * read / total:.1f}% and rendering {100 * render / total:.1f}% (EXR writing, "
        f"{write:.1f} s in all, overlaps the next frame's render); reading USD is "
        f"{100 * read / (read + render):.2f}% of read + compute"
    )
    return 0


def _is_float(word: str) -> bool:
    try:
        float(word)
    except ValueError:
        return False
    return True


if __name__ == "__main__":
    sys.exit(run())
