"""Render light shafts from geometry held in numpy arrays, then composite and save.

    python examples/render_from_arrays.py out/example

A grid of floating tiles casts shafts onto a ground plane; the volume layer is written as a
multi-layer EXR, composited over a flat grey beauty, and previewed as PNG.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

import crepuscular


def tiles(count: int, size: float, height: float, spacing: float) -> tuple[np.ndarray, np.ndarray]:
    corners = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], dtype=np.float32) * size
    positions, triangles = [], []
    for j in range(count):
        for i in range(count):
            offset = np.array([i * spacing, j * spacing, height], dtype=np.float32)
            base = len(positions) * 4
            positions.append(corners + offset - [count * spacing / 2, count * spacing / 2, 0])
            triangles += [[base, base + 1, base + 2], [base, base + 2, base + 3]]
    return np.concatenate(positions), np.asarray(triangles, dtype=np.uint32)


def main(out_dir: Path) -> int:
    out_dir.mkdir(parents=True, exist_ok=True)
    tile_positions, tile_triangles = tiles(count=8, size=0.8, height=4.0, spacing=1.2)
    ground = np.array([[-40, -40, 0], [40, -40, 0], [40, 40, 0], [-40, 40, 0]], dtype=np.float32)
    positions = np.concatenate([ground, tile_positions])
    triangles = np.concatenate([[[0, 1, 2], [0, 2, 3]], tile_triangles + 4]).astype(np.uint32)
    object_ids = np.concatenate([[1, 1], np.full(len(tile_triangles), 2)]).astype(np.uint32)

    # Camera at (-12, -9, 1.6) looking at the origin's shafts; matrices are column-major.
    eye = np.array([-12.0, -9.0, 1.6])
    forward = -eye / np.linalg.norm(eye) + [0, 0, 0.12]
    back = -forward / np.linalg.norm(forward)
    right = np.cross([0, 0, 1], back)
    right /= np.linalg.norm(right)
    up = np.cross(back, right)
    world_from_camera = np.eye(4)
    world_from_camera[:3, 0], world_from_camera[:3, 1], world_from_camera[:3, 2] = right, up, back
    world_from_camera[:3, 3] = eye

    layers = crepuscular.render_arrays(
        positions=positions,
        triangles=triangles,
        object_ids=object_ids,
        camera={
            "world_from_camera": world_from_camera.T.ravel().tolist(),
            "projection": {"kind": "perspective", "focal_length": 28.0},
            "clip_start": 0.1,
            "clip_end": 500.0,
            "width": 640,
            "height": 360,
        },
        sun={"direction": [0.25, 0.35, -1.0], "strength": 6.0},
        medium={"extinction": 0.06, "anisotropy": 0.4},
        settings={"steps": 512, "max_distance": 40.0},
        progress=lambda fraction: print(f"\r{fraction:6.1%}", end="", file=sys.stderr),
    )
    print(file=sys.stderr)
    crepuscular.write_exr(out_dir / "tiles.exr", layers)
    beauty = np.full((layers.height, layers.width, 4), [0.18, 0.18, 0.18, 1.0], dtype=np.float32)
    composited = crepuscular.composite(layers.volume, beauty)
    crepuscular.write_preview_png(out_dir / "tiles.png", composited)
    print(f"wrote {out_dir / 'tiles.exr'} and {out_dir / 'tiles.png'}")
    return 0


if __name__ == "__main__":
    sys.exit(main(Path(sys.argv[1] if len(sys.argv) > 1 else "out/example")))
