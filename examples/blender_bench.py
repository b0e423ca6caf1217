"""Benchmark of the Blender extension on the built-in `tree` scene at 1920x1080.

Run with the project's venv after `make addon`:

    .venv/bin/python examples/blender_bench.py [--runs 5]

It installs the extension zip into a temporary Blender user folder, builds the `tree`
scene in Blender (its meshes, camera and sun from `crepuscular.builtin_scene("tree")`), and
reports medians of:
- the added cost of one F12 frame, split into export (depsgraph to arrays), core (the
  layers) and composite (pixel filter and the compositor's image), and F12 with and without
  shafts (Cycles at 1 sample, so that the beauty is cheap and the difference shows);
- one viewport preview update at 1/2 resolution (export plus core, as the worker runs it).
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
os.environ["BLENDER_USER_RESOURCES"] = tempfile.mkdtemp(prefix="crepuscular-bench-")

import bpy  # noqa: E402
import numpy as np  # noqa: E402

import crepuscular  # noqa: E402

sys.path.insert(0, str(ROOT / "tests" / "blender"))
import blender_scenes  # noqa: E402


def build_tree_scene(width: int, height: int) -> bpy.types.Scene:
    source = crepuscular.builtin_scene("tree")
    scene = bpy.context.scene
    scene.render.resolution_x, scene.render.resolution_y = width, height
    scene.render.resolution_percentage = 100
    for mesh_desc in source["meshes"]:
        blender_scenes.add_mesh(
            scene,
            mesh_desc.get("name") or "mesh",
            mesh_desc["positions"],
            mesh_desc["triangles"],
            world_from_object=np.asarray(mesh_desc["world_from_object"], float).reshape(4, 4).T,
        )
    cam = source["camera"]
    camera = blender_scenes.add_camera(
        scene,
        np.asarray(cam["world_from_camera"], dtype=float).reshape(4, 4).T,
        lens=cam["projection"]["focal_length"],
    )
    camera.data.clip_start, camera.data.clip_end = cam["clip_start"], cam["clip_end"]
    sun = blender_scenes.add_sun(scene, source["sun"]["direction"], strength=8.0)
    settings = sun.data.crepuscular
    settings.method, settings.shadow_map_size = "prefiltered", 1024
    settings.max_distance = source["render"]["max_distance"]
    scene.crepuscular.extinction = source["medium"]["extinction"]
    scene.crepuscular.anisotropy = source["medium"]["anisotropy"]
    scene.render.engine = "CYCLES"
    scene.cycles.samples = 1
    scene.cycles.use_denoising = False
    scene.render.filepath = tempfile.mkdtemp(prefix="crepuscular-bench-out-") + "/f_"
    return scene


def median_time(function, runs: int) -> float:
    times = []
    for _ in range(runs):
        start = time.perf_counter()
        function()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=5)
    parser.add_argument("--width", type=int, default=1920)
    parser.add_argument("--height", type=int, default=1080)
    parser.add_argument("--edge-samples", type=int, default=None)
    parser.add_argument("--method", default="prefiltered")
    parser.add_argument(
        "--cycles-samples",
        type=int,
        default=0,
        help="also time Cycles rendering the same shafts with a fog box, at this sample "
        "count, at 1/4 of the size per axis (the time is then scaled by 16)",
    )
    args = parser.parse_args()
    addon = blender_scenes.install_addon()
    bpy.ops.wm.read_factory_settings(use_empty=True)
    addon = blender_scenes.enable_addon()
    scene = build_tree_scene(args.width, args.height)
    depsgraph = bpy.context.evaluated_depsgraph_get()
    export, render = addon.export, addon.render
    triangles = len(export.export_geometry(depsgraph).triangles)
    settings = scene.objects["Sun"].data.crepuscular
    settings.method = args.method
    if args.edge_samples is not None:
        settings.edge_samples = args.edge_samples
    print(
        f"tree scene: {triangles} triangles, {args.width}x{args.height}, "
        f"{settings.method}, shadow map {settings.shadow_map_size}, "
        f"edge samples {settings.edge_samples}, {os.cpu_count()} CPUs"
    )

    t_cold = median_time(lambda: export.frame_inputs(scene, depsgraph), args.runs)
    print(f"export without the cache: {t_cold:.3f} s")
    cache = export.GeometryCache()
    export.frame_inputs(scene, depsgraph, cache=cache)  # warm the static-geometry cache
    t_export = median_time(lambda: export.frame_inputs(scene, depsgraph, cache=cache), args.runs)
    inputs = export.frame_inputs(scene, depsgraph, cache=cache)
    t_core = median_time(lambda: crepuscular.render_arrays(**inputs.kwargs), args.runs)
    layers = crepuscular.render_arrays(**inputs.kwargs)

    def composite() -> None:
        volume = render.match_pixel_filter(layers.volume, 1.5, settings.edge_samples)
        render.set_volume_image(volume)

    t_composite = median_time(composite, args.runs)
    print(
        f"F12 added cost: export {t_export:.3f} s (cached geometry), core {t_core:.3f} s, "
        f"composite {t_composite:.3f} s, total {t_export + t_core + t_composite:.3f} s"
    )

    def f12() -> None:
        bpy.ops.render.render()

    settings.enabled = False
    t_plain = median_time(f12, max(1, args.runs // 2))
    settings.enabled = True
    scene.crepuscular.write_layers = False
    t_shafts = median_time(f12, max(1, args.runs // 2))
    print(
        f"F12 (Cycles, 1 spp): {t_plain:.3f} s without shafts, {t_shafts:.3f} s with "
        f"(added {t_shafts - t_plain:.3f} s, including the compositor)"
    )

    scene.crepuscular.preview = True
    scene.crepuscular.preview_scale = "2"
    controller = addon.preview.PreviewController(debounce=0.0)

    def preview_update() -> None:
        controller.mark_dirty()
        controller.step(scene, bpy.context.evaluated_depsgraph_get())
        controller.wait()

    t_preview = median_time(preview_update, args.runs)
    print(
        f"viewport preview update at 1/2 resolution: {t_preview:.3f} s "
        "(export on the main thread plus the core on the worker)"
    )
    scene.crepuscular.preview = False
    if args.cycles_samples:
        time_cycles(scene, args)


def time_cycles(scene: bpy.types.Scene, args: argparse.Namespace) -> None:
    """Cycles' own single-scattered shafts: the tree in a fog box, black surfaces and world,
    no bounces, shafts off so that Cycles renders the fog itself."""
    box = np.diag([40.0, 40.0, 15.0, 1.0])
    box[:3, 3] = [0.0, 0.0, 15.0]
    material = blender_scenes.volume_material(
        "scatter",
        Color=(1, 1, 1, 1),
        Density=scene.crepuscular.extinction,
        Anisotropy=scene.crepuscular.anisotropy,
    )
    blender_scenes.add_fog_box(scene, box, material)
    black = blender_scenes.black_material(0.0)
    for obj in scene.objects:
        if obj.type == "MESH" and obj.name != "Fog":
            obj.data.materials.clear()
            obj.data.materials.append(black)
    scene.objects["Sun"].data.crepuscular.enabled = False
    blender_scenes.setup_cycles(
        scene, width=args.width // 4, height=args.height // 4, samples=args.cycles_samples
    )
    scene.render.filepath = tempfile.mkdtemp(prefix="crepuscular-bench-cycles-") + "/c.exr"
    started = time.perf_counter()
    bpy.ops.render.render(write_still=True)
    seconds = time.perf_counter() - started
    small = f"{args.width // 4}x{args.height // 4}"
    print(
        f"Cycles fog box, {args.cycles_samples} spp at {small}: {seconds:.1f} s, "
        f"about {16 * seconds:.0f} s scaled to {args.width}x{args.height}"
    )


if __name__ == "__main__":
    main()
