"""Fixtures for the tests under real Blender (the `bpy` module): the extension is installed
once per session from its zip with Blender's own operator, into the temporary user
resources that tests/conftest.py sets up, and every test starts from a clean scene."""

from __future__ import annotations

from collections.abc import Iterator
from types import ModuleType

import pytest

bpy = pytest.importorskip("bpy")

import blender_scenes  # noqa: E402


@pytest.fixture(scope="session")
def installed() -> ModuleType:
    """The extension package, installed from the zip and enabled."""
    return blender_scenes.install_addon()


@pytest.fixture
def addon(installed: ModuleType) -> Iterator[ModuleType]:
    """A factory-fresh empty scene with the extension enabled."""
    module = blender_scenes.reset()
    yield module
    module.preview.CONTROLLER.cancel()
