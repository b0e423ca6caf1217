"""Crepuscular for Blender 5.0: stylized volumetric light shafts of sun lamps, rendered by
the crepuscular core (bundled wheel) and composited over F12 and animation renders.

Modules register in order and unregister in reverse: properties, render (operator and
handlers), ui (panels and small operators), preview (timer and draw callback), usd_hook
(the USD export hook).
"""

from __future__ import annotations

from . import preview, properties, render, ui, usd_hook

MODULES = (properties, render, ui, preview, usd_hook)


def register() -> None:
    for module in MODULES:
        module.register()


def unregister() -> None:
    for module in reversed(MODULES):
        module.unregister()
