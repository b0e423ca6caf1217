"""The Blender part of `make demo`: installs the extension zip into a temporary Blender user
folder, builds a small scene procedurally through it (a torus over a ground plane, a sun with
stylized shafts and a fog box with a white Volume Scatter), saves it as a .blend, and renders
it with F12 semantics in background mode.

    .venv/bin/python examples/blender_demo.py OUT_DIR

Writes OUT_DIR/torus.blend, the composited frame OUT_DIR/torus_0001.exr and .png (Blender's
own render output through the add-on's compositor group), and the layers
OUT_DIR/torus_crepuscular_0001.exr.
"""

from __future__ import annotations

import os
import sys
import tempfile
import time
from pathlib import Path

os.environ["BLENDER_USER_RESOURCES"] = tempfile.mkdtemp(prefix="crepuscular-demo-")

import bpy
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "blender"))
import blender_scenes


def build(out: Path) -> bpy.types.Scene:
    scene = bpy.context.scene
    blender_scenes.setup_cycles(scene, width=480, height=270, samples=16)
    scene.world.node_tree.nodes["Background"].inputs["Strength"].default_value = 0.2
    scene.cycles.max_bounces = 2
    blender_scenes.add_camera(scene, blender_scenes.look_at((-10, 9, 2.5), (0, 0, 3.0)), lens=28)
    sun = blender_scenes.add_sun(scene, (-0.45, 0.35, -0.8), strength=4.0)
    settings = sun.data.crepuscular
    settings.shadow_map_size, settings.max_distance = 1024, 40.0
    grey = blender_scenes.black_material(0.15)
    blender_scenes.add_quad(
        scene, "Ground", [(-20, -20, 0), (20, -20, 0), (20, 20, 0), (-20, 20, 0)], grey
    )
    bpy.ops.mesh.primitive_torus_add(
        location=(0, 0, 3.5), rotation=(0.3, 0, 0), major_radius=1.6, minor_radius=0.45
    )
    bpy.context.active_object.data.materials.append(grey)
    fog = np.diag([8.0, 8.0, 4.0, 1.0])
    fog[:3, 3] = [0.0, 0.0, 4.0]
    material = blender_scenes.volume_material(
        "scatter", Color=(1, 1, 1, 1), Density=0.1, Anisotropy=0.5
    )
    blender_scenes.add_fog_box(scene, fog, material)
    scene.render.image_settings.file_format = "OPEN_EXR"
    scene.render.filepath = str(out / "torus_")
    bpy.ops.wm.save_as_mainfile(filepath=str(out / "torus.blend"))
    return scene


def main() -> None:
    if len(sys.argv) != 2:
        raise SystemExit(__doc__)
    out = Path(sys.argv[1]).resolve()
    out.mkdir(parents=True, exist_ok=True)
    blender_scenes.install_addon()
    blender_scenes.reset()
    scene = build(out)
    scene.frame_end = scene.frame_start
    started = time.perf_counter()
    bpy.ops.render.render(animation=True)  # F12 semantics for frame 1, in background mode
    print(f"rendered in {time.perf_counter() - started:.1f} s")
    import crepuscular

    channels = crepuscular.read_exr(out / "torus_0001.exr")
    rgba = np.stack([channels[c] for c in "RGBA"], axis=-1)
    crepuscular.write_preview_png(out / "torus_0001.png", rgba)
    for name in ("torus.blend", "torus_0001.exr", "torus_0001.png", "torus_crepuscular_0001.exr"):
        print(out / name)


if __name__ == "__main__":
    main()
