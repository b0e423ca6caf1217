"""UsdSkel: the points of skinned meshes posed at a time code, as UsdSkel defines them.

A mesh bound to a Skeleton stores its rest shape; what renders (and casts shadows) is that
shape with the bound SkelAnimation's blend-shape weights applied, then skinned by its
joints, in the skeleton's space. The mesh's own transform is ignored, as UsdSkel says: its
`geomBindTransform` takes its place. Blender's USD exporter writes armatures and shape keys
this way by default, so a posed character read at rest casts the wrong shadow.

Every computation here is pxr's own (UsdSkel.Cache, SkinningQuery, BlendShapeQuery), in
C++; this module only finds the bindings once per SkelRoot and checks every falsy return.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
from pxr import Sdf, Usd, UsdSkel, Vt

__all__ = ["SkinnedMeshes", "SkinningError"]

F64 = npt.NDArray[np.float64]


class SkinningError(ValueError):
    """A skinned mesh whose pose cannot be computed; the message names the prim."""


@dataclass(frozen=True)
class _Binding:
    skinning: UsdSkel.SkinningQuery
    skeleton: UsdSkel.SkeletonQuery
    blend_shapes: UsdSkel.BlendShapeQuery | None


class SkinnedMeshes:
    """The skinned meshes under the SkelRoots of a stage, found once per root.

    Bindings depend on the stage's structure, not on time, so a collector that reads many
    frames finds them on the first and poses them on every one.
    """

    def __init__(self, predicate: Usd._PrimFlagsPredicate) -> None:
        self._predicate = predicate
        self._cache = UsdSkel.Cache()
        self._populated: set[Sdf.Path] = set()
        self._bindings: dict[Sdf.Path, _Binding] = {}
        # Each skeleton's skinning transforms at `_time`: a character's meshes share them.
        self._time: Usd.TimeCode | None = None
        self._joint_xforms: dict[Sdf.Path, Vt.Matrix4dArray | None] = {}

    def add_root(self, prim: Usd.Prim) -> None:
        """Finds the skinned meshes under the SkelRoot `prim` (once per root)."""
        path = prim.GetPath()
        if path in self._populated:
            return
        self._populated.add(path)
        root = UsdSkel.Root(prim)
        if not self._cache.Populate(root, self._predicate):
            raise SkinningError(f"{path}: its skeleton bindings could not be read")
        for binding in self._cache.ComputeSkelBindings(root, self._predicate):
            skeleton = self._cache.GetSkelQuery(binding.GetSkeleton())
            if not skeleton:
                continue
            for skinning in binding.GetSkinningTargets():
                # Any surface: an implicit one bound rigidly (a prop in a hand) follows its
                # joint as a mesh does.
                target = skinning.GetPrim()
                blend_shapes = None
                if skinning.HasBlendShapes():
                    blend_shapes = UsdSkel.BlendShapeQuery(UsdSkel.BindingAPI(target))
                self._bindings[target.GetPath()] = _Binding(skinning, skeleton, blend_shapes)

    def is_skinned(self, prim: Usd.Prim) -> bool:
        return prim.GetPath() in self._bindings

    def posed_points(
        self,
        prim: Usd.Prim,
        rest_points: F64,
        time: Usd.TimeCode,
    ) -> tuple[F64, Usd.Prim]:
        """The mesh's points posed at `time`, and the prim whose space they are in: the
        skeleton's where joints skin them, else the mesh's own."""
        binding = self._bindings[prim.GetPath()]
        where = str(prim.GetPath())
        points = Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(rest_points, dtype=np.float32))
        if binding.blend_shapes is not None:
            _apply_blend_shapes(binding, points, time, where)
        if binding.skinning.HasJointInfluences():
            joint_xforms = self._skinning_transforms(binding.skeleton, time)
            if joint_xforms is None:
                raise SkinningError(
                    f"{where}: its skeleton's joint transforms could not be computed"
                )
            if not binding.skinning.ComputeSkinnedPoints(joint_xforms, points, time):
                raise SkinningError(
                    f"{where}: its {len(points)} points could not be skinned (do its joint "
                    "influences match its points and its skeleton's joints?)"
                )
            space = binding.skeleton.GetPrim()
        else:
            # Blend shapes alone deform the mesh where it stands.
            space = prim
        return np.array(points, dtype=np.float64).reshape(-1, 3), space

    def _skinning_transforms(
        self, skeleton: UsdSkel.SkeletonQuery, time: Usd.TimeCode
    ) -> Vt.Matrix4dArray | None:
        """The skeleton's skinning transforms at `time`, computed once per frame."""
        if time != self._time:
            self._time = time
            self._joint_xforms.clear()
        path = skeleton.GetPrim().GetPath()
        if path not in self._joint_xforms:
            self._joint_xforms[path] = skeleton.ComputeSkinningTransforms(time)
        return self._joint_xforms[path]


def _apply_blend_shapes(
    binding: _Binding, points: Vt.Vec3fArray, time: Usd.TimeCode, where: str
) -> None:
    """Adds the animation's weighted blend-shape offsets (and inbetweens) to `points`."""
    animation = binding.skeleton.GetAnimQuery()
    if not animation:
        return
    weights = animation.ComputeBlendShapeWeights(time)
    if weights is None or len(weights) == 0:
        return
    mapper = binding.skinning.GetBlendShapeMapper()
    if mapper is None:
        return
    weights = mapper.Remap(weights)
    query = binding.blend_shapes
    assert query is not None
    computed = query.ComputeSubShapeWeights(weights)
    if not computed:
        raise SkinningError(f"{where}: its blend-shape weights could not be computed")
    sub_shape_weights, blend_shape_indices, sub_shape_indices = computed
    if not query.ComputeDeformedPoints(
        sub_shape_weights,
        blend_shape_indices,
        sub_shape_indices,
        query.ComputeBlendShapePointIndices(),
        query.ComputeSubShapePointOffsets(),
        points,
    ):
        raise SkinningError(f"{where}: its blend shapes could not be applied")
