"""Small scenes for the bake tests, built with explicit UVs (no unwrapper)."""
import numpy as np

from prtt_addon.core.model.scene import Scene
from prtt_addon.dev.bench import meshgen as mg


def planar_uvs(m: mg.Mesh, axes=(0, 1)) -> np.ndarray:
    """Corner UVs by projecting onto two axes, normalised to [0, 1]."""
    p = m.vertices[:, list(axes)]
    lo, hi = p.min(0), p.max(0)
    uv = (p - lo) / np.where(hi > lo, hi - lo, 1.0)
    return uv[m.faces]


def scene_from(objects, resolution=64) -> Scene:
    """objects: list of (name, Mesh, uvs (F, 3, 2)); one texture set per object."""
    pos, nrm, uv, sid = [], [], [], []
    for i, (_name, m, u) in enumerate(objects):
        pos.append(m.corner_positions())
        nrm.append(m.corner_normals())
        uv.append(u)
        sid.append(np.full(m.n_faces, i))
    names = [o[0] for o in objects]
    res = resolution if isinstance(resolution, (list, tuple)) else [resolution] * len(objects)
    return Scene(positions=np.concatenate(pos), normals=np.concatenate(nrm), uvs=np.concatenate(uv),
                 set_id=np.concatenate(sid), set_names=names,
                 set_resolution=np.array([[r, r] for r in res]),
                 object_id=np.concatenate(sid), object_names=names)


def floor_and_box(scale=1.0, floor_size=4.0, box=(1.0, 1.0, 1.0), res=64, subdiv=1) -> Scene:
    f = mg.plane(floor_size, subdiv=subdiv).transformed(scale=scale)
    b = mg.box(box, (0, 0, box[2] / 2)).transformed(scale=scale)
    return scene_from([("floor", f, planar_uvs(f)), ("box", b, mg.box_face_uvs(b))], res)


def floor_and_box_with_every_part(res=8) -> Scene:
    """floor_and_box with every optional part of the job format: a normal map on
    two triangles (strength 0.7), tangents, a material with a base-colour
    texture, material UVs. Validated."""
    from prtt_addon.core.model.scene import NormalMap, validate
    sc = floor_and_box(res=res)
    T = sc.n_triangles
    sc.normal_maps = [NormalMap(np.full((4, 4, 3), 0.5, np.float32), 0.7)]
    sc.nm_index = np.full(T, -1, np.int32)
    sc.nm_index[:2] = 0
    sc.nm_uvs = sc.uvs.copy()
    sc.tangents = np.zeros((T, 3, 4), np.float32)
    sc.tangents[..., 0] = 1
    sc.tangents[..., 3] = 1
    sc.material_id = np.zeros(T, np.int32)
    sc.materials = [{"name": "m", "base_color": [0.5, 0.5, 0.5], "roughness": 0.3, "base_color_texture": 0}]
    sc.textures = [np.full((4, 4, 3), 0.25, np.float32)]
    sc.mat_uvs = sc.uvs.copy()
    validate(sc)
    return sc


def random_islands(rng, H: int, W: int, *, rects: int = 12, most: int = 8, margin: int = 4,
                   singles: int = 20) -> np.ndarray:
    """(H, W) bool coverage of ``rects`` random rectangles (sides 1..``most``,
    corners at least ``margin`` texels from the far edges) and ``singles``
    single texels: small islands have the most border."""
    m = np.zeros((H, W), bool)
    for _ in range(rects):
        y, x = rng.integers(0, H - margin), rng.integers(0, W - margin)
        m[y:y + rng.integers(1, most + 1), x:x + rng.integers(1, most + 1)] = True
    m[rng.integers(0, H, singles), rng.integers(0, W, singles)] = True
    return m
