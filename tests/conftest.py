"""Small scene descriptions for the Python API tests."""

from __future__ import annotations

import atexit
import os
import shutil
import tempfile
from collections.abc import Callable
from typing import Any

import pytest

# Blender keeps installed extensions and preferences in its user resource folder. Point it at
# a temporary one before bpy is first imported (here or in a subprocess, which inherits it),
# so that tests never read or change a real user configuration.
if "CREPUSCULAR_TEST_BLENDER_USER" not in os.environ:
    _blender_user = tempfile.mkdtemp(prefix="crepuscular-blender-user-")
    atexit.register(shutil.rmtree, _blender_user, ignore_errors=True)
    os.environ["CREPUSCULAR_TEST_BLENDER_USER"] = _blender_user
    os.environ["BLENDER_USER_RESOURCES"] = _blender_user

from scenes import build_scene, flatten


@pytest.fixture
def scene() -> dict[str, Any]:
    """A fresh 64x36 scene: ground plane plus one occluding quad."""
    return build_scene()


@pytest.fixture
def make_scene() -> Callable[..., dict[str, Any]]:
    return build_scene


@pytest.fixture
def scene_arrays(scene: dict[str, Any]) -> dict[str, Any]:
    """`render_arrays` keyword arguments for the `scene` fixture."""
    return flatten(scene)


@pytest.fixture
def to_arrays() -> Callable[[dict[str, Any]], dict[str, Any]]:
    """The `flatten` helper: scene dict -> `render_arrays` keyword arguments."""
    return flatten
