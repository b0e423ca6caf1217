"""Real Blender 5 multi-part EXRs: rendered live with Cycles, read back, and used as the
renderer depth of a crepuscular render with the same camera."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import crepuscular

SCRIPT = Path(__file__).parent.parent / "core" / "tests" / "data" / "make_blender_multipart.py"


@pytest.fixture(scope="module")
def blender_exr(tmp_path_factory: pytest.TempPathFactory) -> Path:
    pytest.importorskip("bpy")
    out = tmp_path_factory.mktemp("blender") / "multipart.exr"
    subprocess.run(
        [sys.executable, str(SCRIPT), str(out)], check=True, capture_output=True, timeout=300
    )
    return out


def test_reads_blender_parts_and_channels(blender_exr: Path) -> None:
    channels = crepuscular.read_exr(blender_exr)
    for name in ("ViewLayer.Combined.R", "ViewLayer.Combined.A", "ViewLayer.Depth.Z"):
        assert name in channels, sorted(channels)
        assert channels[name].shape == (6, 8)
    depth = channels["ViewLayer.Depth.Z"]
    alpha = channels["ViewLayer.Combined.A"]
    # The cube fills the top-left; the bottom-right sees background (Blender writes 1e10).
    assert alpha[1, 1] == pytest.approx(1.0)
    assert depth[1, 1] == pytest.approx(3.5, abs=1e-4)
    assert alpha[5, 7] == 0.0
    assert depth[5, 7] > 1e9


def test_blender_depth_drives_a_render_with_the_same_camera(blender_exr: Path) -> None:
    planar = crepuscular.read_exr(blender_exr)["ViewLayer.Depth.Z"]
    # Blender's camera: at (0, -4, 0) rotated 90° about X (looking along +Y), 50 mm lens,
    # 36 mm sensor, automatic fit, 8 by 6 pixels.
    world_from_camera = np.array(
        [[1, 0, 0, 0], [0, 0, -1, -4], [0, 1, 0, 0], [0, 0, 0, 1]], dtype=np.float32
    )
    scene = {
        "version": 1,
        "camera": {
            "world_from_camera": world_from_camera.T.ravel().tolist(),
            "projection": {"kind": "perspective", "focal_length": 50.0},
            "clip_start": 0.1,
            "clip_end": 100.0,
            "width": 8,
            "height": 6,
        },
        "sun": {"direction": [0.0, 0.3, -1.0]},
        "medium": {"extinction": 0.2},
        "meshes": [
            {
                "object_id": 1,
                "positions": [[-50, -50, -5], [50, -50, -5], [50, 50, -5], [-50, 50, -5]],
                "triangles": [[0, 1, 2], [0, 2, 3]],
            }
        ],
        "render": {"shadow_map_size": 64, "steps": 32, "max_distance": 20.0},
    }
    layers = crepuscular.render(scene, camera_depth=planar, depth_kind="planar")
    # Ray distance = planar depth * |(x, y, -1)| on Blender's view plane.
    pixel = 36.0 / 50.0 / 8.0
    xs = (np.arange(8) + 0.5 - 4.0) * pixel
    ys = (3.0 - (np.arange(6) + 0.5)) * pixel
    stretch = np.sqrt(xs[None, :] ** 2 + ys[:, None] ** 2 + 1.0)
    surface = planar < 100.0
    np.testing.assert_allclose(layers.depth[surface], (planar * stretch)[surface], rtol=1e-5)
    assert np.all(layers.depth[~surface] == 20.0)
    # Shorter segments in front of the cube scatter less light than background rays.
    assert layers.volume[0, 0, 3] < layers.volume[5, 7, 3]
