"""Objects' triangles -> one bake :class:`~prtt_addon.core.model.scene.Scene`.

The one assembly path of the Blender export (prtt_addon/blender/scene/job.py)
and of :func:`prtt_addon.dev.bench.meshgen.assemble`: each object (or instance)
is a :class:`MeshPart` in world space, already laid out in its texture set;
:func:`assemble_parts` concatenates them in order (object ids follow the
list) and fills what a part leaves out with the format's defaults.
"""
from __future__ import annotations

import dataclasses

import numpy as np

from .scene import NormalMap, Scene


@dataclasses.dataclass
class MeshPart:
    """One object's (or instance's) triangles in world space and where they go.

    Arrays are per triangle corner, T triangles. Optional arrays left None
    take the defaults of docs/format.md: an occluder's UVs are zeros, a
    triangle without a normal map has ``nm_index`` -1, UVs zeros and tangent
    (1, 0, 0, +1).
    """

    name: str
    positions: np.ndarray                 # (T, 3, 3) world
    normals: np.ndarray                   # (T, 3, 3) world, unit
    uvs: np.ndarray | None = None         # (T, 3, 2) in its set's [0, 1] square; None: an occluder
    set_index: int = -1                   # texture set; -1: an occluder (shadows, absorbs bounce light)
    material: np.ndarray | None = None    # (T,) index into the scene's materials (None: material 0)
    mat_uvs: np.ndarray | None = None     # (T, 3, 2) UVs its material textures are sampled with
    nm_index: np.ndarray | None = None    # (T,) normal map per triangle, -1 none
    nm_uvs: np.ndarray | None = None      # (T, 3, 2) UVs its normal map is sampled with
    tangents: np.ndarray | None = None    # (T, 3, 4) world tangent xyz and bitangent sign

    @property
    def triangles(self) -> int:
        return int(self.positions.shape[0])


def _joined(parts, field: str, default) -> np.ndarray:
    """``field`` of every part, concatenated; ``default(T)`` where a part has none."""
    return np.concatenate([getattr(p, field) if getattr(p, field) is not None else default(p.triangles)
                           for p in parts])


def default_tangents(T: int) -> np.ndarray:
    """(T, 3, 4) float32 tangents of triangles without a normal map: (1, 0, 0, +1)."""
    t = np.zeros((T, 3, 4), np.float32)
    t[..., 0] = 1.0
    t[..., 3] = 1.0
    return t


def assemble_parts(parts: list[MeshPart], set_names: list, set_resolution, *, materials: list | None = None,
                   textures: list | None = None, normal_maps: list[NormalMap] | None = None) -> Scene:
    """A bake Scene from parts, in order.

    set_names, set_resolution [[w, h]]: the texture sets the parts'
    ``set_index`` refers to. ``materials``: material specs (docs/format.md);
    None leaves the scene without materials (every triangle the default
    one). ``textures`` and ``normal_maps``: the images materials and
    ``nm_index`` refer to. Raises SceneError (core.model.scene.validate) for an
    inconsistent result.
    """
    normal_maps = list(normal_maps or [])
    with_materials = materials is not None
    return Scene(
        positions=np.concatenate([p.positions for p in parts]),
        normals=np.concatenate([p.normals for p in parts]),
        uvs=_joined(parts, "uvs", lambda T: np.zeros((T, 3, 2))),
        set_id=np.concatenate([np.full(p.triangles, p.set_index, np.int32) for p in parts]),
        set_names=list(set_names), set_resolution=np.array(set_resolution),
        object_id=np.concatenate([np.full(p.triangles, i, np.int32) for i, p in enumerate(parts)]),
        object_names=[p.name for p in parts],
        nm_index=_joined(parts, "nm_index", lambda T: np.full(T, -1, np.int32)) if normal_maps else None,
        nm_uvs=_joined(parts, "nm_uvs", lambda T: np.zeros((T, 3, 2))) if normal_maps else None,
        tangents=_joined(parts, "tangents", default_tangents) if normal_maps else None,
        normal_maps=normal_maps,
        material_id=_joined(parts, "material", lambda T: np.zeros(T, np.int32)) if with_materials else None,
        materials=list(materials) if with_materials else [],
        mat_uvs=_joined(parts, "mat_uvs", lambda T: np.zeros((T, 3, 2))) if with_materials else None,
        textures=list(textures or []))
