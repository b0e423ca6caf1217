"""Value nodes between a cutout's image and the alpha it gives: Math, Invert, Map Range and
Color Ramp nodes that artists put there to sharpen or invert a mask. Opening a file whose
scenes all render with EEVEE, Blender 4.2 and later put a Math node set to Greater Than, at
the old clip threshold, into each material of the Alpha Clip blend mode, so leaf cards from
older files arrive so.

Cycles applies such a chain to the filtered texture value, and lets light through by the
alpha it gives; the core clips a mask's filtered value at a threshold. Where the texture
values whose alpha reaches one half form one interval from 0 or to 1 (the chain is
monotonic there, as a Greater Than step is), the same cut is a threshold on the raw value,
inverted for a falling chain. A chain that cuts elsewhere is refused with a note.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from . import node_links

#: Scalar functions of the chain's value, as Cycles computes each Math operation (its
#: "safe" division and power give 0 where they are undefined).
_OPERATIONS: dict[str, Callable[[np.ndarray, float, float], np.ndarray]] = {
    "ADD": lambda a, b, _: a + b,
    "SUBTRACT": lambda a, b, _: a - b,
    "MULTIPLY": lambda a, b, _: a * b,
    "DIVIDE": lambda a, b, _: np.divide(a, b, out=np.zeros_like(a), where=b != 0),
    "MULTIPLY_ADD": lambda a, b, c: a * b + c,
    "POWER": lambda a, b, _: np.where(
        (a >= 0) | (np.floor(b) == b), np.power(np.abs(a), b) * np.sign(a) ** b, 0.0
    ),
    "MINIMUM": lambda a, b, _: np.minimum(a, b),
    "MAXIMUM": lambda a, b, _: np.maximum(a, b),
    "LESS_THAN": lambda a, b, _: (a < b).astype(np.float64),
    "GREATER_THAN": lambda a, b, _: (a > b).astype(np.float64),
    "ROUND": lambda a, _b, _c: np.floor(a + 0.5),
    "FLOOR": lambda a, _b, _c: np.floor(a),
    "CEIL": lambda a, _b, _c: np.ceil(a),
    "ABSOLUTE": lambda a, _b, _c: np.abs(a),
}

#: The node types a chain may pass through.
CHAIN_NODES = {"ShaderNodeMath", "ShaderNodeInvert", "ShaderNodeMapRange", "ShaderNodeValToRGB"}

#: Where the chain's value is sampled: texture values are saturated to [0, 1].
_SAMPLES = np.linspace(0.0, 1.0, 4097)


@dataclass(frozen=True)
class Cut:
    """How a mask cuts the raw texture value v: where `1 - v` (if `invert`) or v reaches
    `threshold`; `solid` or `empty` where every value cuts alike."""

    threshold: float = 0.5
    invert: bool = False
    solid: bool = False
    empty: bool = False


class ChainError(ValueError):
    """A chain this cannot map; the message names the node."""


Step = Callable[[np.ndarray], np.ndarray]


def follow(source: node_links.Traced, where: str) -> tuple[list[Step], node_links.Traced]:
    """The steps of the chain of value nodes `source` comes through, nearest the alpha
    first, and the socket that feeds the chain (the texture's, where it is one)."""
    steps: list[Step] = []
    while source.is_linked and source.node.bl_idname in CHAIN_NODES:
        step, source = _step(source, where)
        steps.append(step)
    return steps, source


def cut_of(steps: list[Step], alpha: Callable[[np.ndarray], np.ndarray], where: str) -> Cut:
    """The cut of raw texture values v whose alpha, `alpha` of the chain's value, reaches
    one half."""
    value = _SAMPLES.copy()
    for step in reversed(steps):
        value = np.nan_to_num(step(value), nan=0.0, posinf=1.0, neginf=0.0)
    levels = alpha(value)
    solid = levels >= 0.5
    if solid.all():
        return Cut(solid=True)
    if not solid.any():
        return Cut(empty=True)
    first, last = int(np.argmax(solid)), len(solid) - 1 - int(np.argmax(solid[::-1]))
    if solid[first:].all():  # rising: solid from the first solid sample up
        return Cut(threshold=_crossing(levels, first - 1))
    if solid[: last + 1].all():  # falling: solid up to the last solid sample
        return Cut(threshold=1.0 - _crossing(levels, last), invert=True)
    raise ChainError(f"{where}: its alpha's nodes cut the texture in more than one band")


def _crossing(levels: np.ndarray, k: int) -> float:
    """Where the alpha crosses one half between samples k and k + 1, linearly."""
    low, high = float(levels[k]), float(levels[k + 1])
    t = 0.5 if high == low else min(max((0.5 - low) / (high - low), 0.0), 1.0)
    return float(_SAMPLES[k] + t * (_SAMPLES[k + 1] - _SAMPLES[k]))


def _step(source: node_links.Traced, where: str) -> tuple[Step, node_links.Traced]:
    """One node of the chain: its function of the value from the one input fed by more
    than a constant, and that input's source."""
    node, groups = source.node, source.groups
    inputs = [socket for socket in node.inputs if socket.enabled]
    traced = [node_links.traced(socket, groups) for socket in inputs]
    varying = [k for k, t in enumerate(traced) if not t.is_constant]
    if len(varying) != 1:
        raise ChainError(
            f"{where}: node '{node.name}' on its alpha takes {len(varying)} varying inputs, not one"
        )
    (k,) = varying

    def constant(name: str, index: int | None = None) -> float:
        socket = inputs[index] if index is not None else node.inputs[name]
        value = node_links.traced(socket, groups).value("VALUE")
        return float(value)

    kind = node.bl_idname
    if kind == "ShaderNodeMath":
        operation = _OPERATIONS.get(node.operation)
        if operation is None:
            raise ChainError(
                f"{where}: Math node '{node.name}' on its alpha is {node.operation}, which "
                "this does not map"
            )
        others = [constant("", j) if j != k else 0.0 for j in range(len(inputs))] + [0.0] * 3

        def math_step(value: np.ndarray) -> np.ndarray:
            operands = [value if j == k else others[j] for j in range(3)]
            result = operation(*operands)
            return np.clip(result, 0.0, 1.0) if node.use_clamp else result

        return math_step, traced[k]
    if kind == "ShaderNodeInvert":
        if inputs[k].name != "Color":
            raise ChainError(f"{where}: Invert node '{node.name}' on its alpha has a varying Fac")
        fac = constant("Fac")
        return (lambda value: (1.0 - fac) * value + fac * (1.0 - value)), traced[k]
    if kind == "ShaderNodeMapRange":
        if node.data_type != "FLOAT" or node.interpolation_type != "LINEAR" or k != 0:
            raise ChainError(
                f"{where}: Map Range node '{node.name}' on its alpha is not a linear float "
                "map of its Value; it casts as opaque"
            )
        low, high = constant("From Min"), constant("From Max")
        to_low, to_high = constant("To Min"), constant("To Max")

        def map_step(value: np.ndarray) -> np.ndarray:
            span = high - low
            t = np.zeros_like(value) if span == 0 else (value - low) / span
            result = to_low + t * (to_high - to_low)
            if node.clamp:
                result = np.clip(result, min(to_low, to_high), max(to_low, to_high))
            return result

        return map_step, traced[k]
    # A Color Ramp, evaluated by Blender itself; its Color reads as luminance.
    ramp = node.color_ramp
    output = source.socket.name

    def ramp_step(value: np.ndarray) -> np.ndarray:
        colours = np.array([ramp.evaluate(float(v)) for v in value], dtype=np.float64)
        if output == "Alpha":
            return colours[:, 3]
        return colours[:, :3] @ node_links.LUMINANCE

    return ramp_step, traced[k]
