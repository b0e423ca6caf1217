"""crepuscular_usd: the USD pipeline step of crepuscular.

Reads a USD stage (meshes, instancing, a camera, a DistantLight with the
`CrepuscularLightAPI` schema) frame by frame into the renderer's scene description,
renders the light-shaft layers, and records what it produced in a USD layer. Importing
this package registers the codeless schema with USD's plug-in registry.
"""

from __future__ import annotations

from crepuscular_usd import schema as _schema

__version__ = "0.1.0"

_schema.register()

from crepuscular_usd.frames import FrameSpecError, FrameSpecIterator  # noqa: E402
from crepuscular_usd.geometry import MeshError, SceneGeometry, triangulate  # noqa: E402
from crepuscular_usd.schema import API_NAME, SchemaError, apply_schema  # noqa: E402
from crepuscular_usd.stage import Frame, StageError, StageReader, open_stage  # noqa: E402

__all__ = [
    "API_NAME",
    "Frame",
    "FrameSpecError",
    "FrameSpecIterator",
    "MeshError",
    "SceneGeometry",
    "SchemaError",
    "StageError",
    "StageReader",
    "__version__",
    "apply_schema",
    "open_stage",
    "triangulate",
]
