"""Following a material's node links as Cycles compiles them: through reroutes, muted
nodes (their pass-through links; an output without one leaves its input unlinked) and
node groups (into a group's active output, and out through its Group Input to the group
node's own sockets), over muted and invalid links as if absent. Constant inputs are read
through Value and RGB nodes and group sockets, with Blender's implicit conversions between
values, colours and vectors. Fog presets and leaf materials from asset libraries come
wrapped in node groups with exposed inputs, and a Value node is how a density is animated.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import bpy
import numpy as np

#: Rec. 709 luminance weights: Blender's colour-to-value conversion in its default
#: scene-linear space.
LUMINANCE = np.array([0.2126, 0.7152, 0.0722])

#: Nodes whose output is a constant that Cycles folds: its value is the output's own.
CONSTANT_NODES = {"ShaderNodeValue", "ShaderNodeRGB"}


class NodeLinkError(ValueError):
    """A constant input fed by a node whose output varies; the message names both."""


@dataclass(frozen=True)
class Traced:
    """Where an input socket's value comes from: the output `socket` of a node that
    computes it, or (`socket.is_output` false) an input left unlinked, whose own value it
    takes. `groups` are the group nodes `socket`'s tree is nested in, outermost first."""

    socket: bpy.types.NodeSocket
    groups: tuple[bpy.types.Node, ...] = ()

    @property
    def node(self) -> bpy.types.Node:
        return self.socket.node

    @property
    def is_linked(self) -> bool:
        return bool(self.socket.is_output)

    @property
    def is_constant(self) -> bool:
        """Whether the value is one everywhere: the input's own, or a Value or RGB node's."""
        return not self.is_linked or self.node.bl_idname in CONSTANT_NODES

    def value(self, as_type: str) -> Any:
        """A constant's value as a socket of `as_type` reads it ("VALUE", "RGBA" or
        "VECTOR"; `_converted`)."""
        return _converted(self.socket.default_value, self.socket.type, as_type)


def _link(socket: bpy.types.NodeSocket) -> bpy.types.NodeLink | None:
    for link in socket.links:
        if link.is_valid and not link.is_muted:
            return link
    return None


def _by_identifier(
    sockets: bpy.types.bpy_prop_collection, identifier: str
) -> bpy.types.NodeSocket | None:
    return next((socket for socket in sockets if socket.identifier == identifier), None)


def _group_output(tree: bpy.types.NodeTree | None) -> bpy.types.Node | None:
    if tree is None:
        return None
    outputs = [node for node in tree.nodes if node.bl_idname == "NodeGroupOutput"]
    return next((node for node in outputs if node.is_active_output), None) or next(
        iter(outputs), None
    )


def traced(socket: bpy.types.NodeSocket, groups: tuple[bpy.types.Node, ...] = ()) -> Traced:
    """Where the input `socket` (of a node nested in `groups`) takes its value from."""
    while True:
        link = _link(socket)
        if link is None:
            return Traced(socket, groups)
        source = link.from_socket
        node = source.node
        if node.bl_idname == "NodeReroute":
            socket = node.inputs[0]
        elif node.mute:
            passing = [link for link in node.internal_links if link.to_socket == source]
            if not passing:
                return Traced(socket, groups)
            socket = passing[0].from_socket
        elif node.bl_idname == "NodeGroupInput":
            # Out to the group node's own socket; unlinked at the top level, or where the
            # group node lacks the socket (an interface edited since).
            outer = _by_identifier(groups[-1].inputs, source.identifier) if groups else None
            if outer is None:
                return Traced(socket, groups)
            socket, groups = outer, groups[:-1]
        elif node.bl_idname == "ShaderNodeGroup":
            output = _group_output(node.node_tree)
            inner = _by_identifier(output.inputs, source.identifier) if output else None
            if inner is None:
                return Traced(socket, groups)
            socket, groups = inner, (*groups, node)
        else:
            return Traced(source, groups)


def _converted(value: object, source_type: str, target_type: str) -> object:
    """`value` of a socket of `source_type` as a socket of `target_type` reads it, as
    Blender converts implicitly: a colour to its luminance, a vector to its mean, a value
    to a grey colour or an even vector."""
    if source_type == target_type or target_type not in ("VALUE", "RGBA", "VECTOR"):
        return value
    if source_type == "VALUE":
        scalar = float(value)  # type: ignore[arg-type]
        return (scalar, scalar, scalar, 1.0) if target_type == "RGBA" else (scalar,) * 3
    components = np.array(value, dtype=np.float64)[:3]
    if target_type == "VALUE":
        return float(LUMINANCE @ components if source_type == "RGBA" else components.mean())
    return (*components, 1.0) if target_type == "RGBA" else tuple(components)


def constant(
    node: bpy.types.Node, name: str, groups: tuple[bpy.types.Node, ...], where: str
) -> Any:
    """The value of input `name` of `node` (nested in `groups`): its own, a group socket's
    or a Value or RGB node's, converted to the input's type. Raises NodeLinkError where
    another node feeds it."""
    socket = node.inputs[name]
    source = traced(socket, groups)
    if not source.is_constant:
        raise NodeLinkError(
            f"{where}: input '{name}' of '{node.name}' must be a constant (its own value, a "
            f"group input's, or a Value or RGB node's), not linked from '{source.node.name}'"
        )
    return source.value(socket.type)
