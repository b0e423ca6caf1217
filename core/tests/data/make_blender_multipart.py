"""Render the tiny multi-part EXR fixture `blender5_multipart.exr` with real Blender (bpy 5.0.x).

Run from the repository root:  .venv/bin/python core/tests/data/make_blender_multipart.py [OUT]
The fixture is committed; the Python tests run this script again into a temporary file, so
the reader is also checked against whatever the installed Blender writes.
"""

import os
import sys

import bpy

OUT = (
    sys.argv[1]
    if len(sys.argv) > 1
    else os.path.join(os.path.dirname(os.path.abspath(__file__)), "blender5_multipart.exr")
)

bpy.ops.wm.read_factory_settings(use_empty=True)
scene = bpy.context.scene

# A unit cube ahead of a camera on the -Y axis, shifted up and left so that it fills the
# top-left of the frame and the bottom-right sees background: a reader that flips rows
# or columns fails the test.
bpy.ops.mesh.primitive_cube_add(size=1.0, location=(-0.7, 0.0, 0.45))
cam_data = bpy.data.cameras.new("Camera")
cam = bpy.data.objects.new("Camera", cam_data)
scene.collection.objects.link(cam)
cam.location = (0.0, -4.0, 0.0)
cam.rotation_euler = (1.5707963267948966, 0.0, 0.0)
scene.camera = cam

light_data = bpy.data.lights.new("Sun", type="SUN")
light = bpy.data.objects.new("Sun", light_data)
scene.collection.objects.link(light)
light.rotation_euler = (0.6, 0.2, 0.3)

scene.render.engine = "CYCLES"
scene.cycles.device = "CPU"
scene.cycles.samples = 8
scene.cycles.use_denoising = False
scene.render.film_transparent = True  # background alpha 0
scene.render.resolution_x = 8
scene.render.resolution_y = 6
scene.render.resolution_percentage = 100

scene.view_layers[0].use_pass_z = True

settings = scene.render.image_settings
# Blender 5.0 selects multilayer through media_type; once set, the only file format on
# offer is OPEN_EXR_MULTILAYER ("OPEN_EXR" is rejected), so it is checked, not assigned.
settings.media_type = "MULTI_LAYER_IMAGE"
assert settings.file_format == "OPEN_EXR_MULTILAYER", settings.file_format
settings.color_depth = "32"  # float (full)
settings.exr_codec = "ZIP"
print("use_exr_interleave =", settings.use_exr_interleave)

scene.render.filepath = OUT
bpy.ops.render.render(write_still=True)
print("wrote", OUT, os.path.getsize(OUT), "bytes")
