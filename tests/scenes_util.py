"""Small scenes for the bake tests, built with explicit UVs (no unwrapper)."""
import numpy as np

from prtt_addon.core import meshgen as mg
from prtt_addon.core.scene import Scene


def planar_uvs(m: mg.Mesh, axes=(0, 1)) -> np.ndarray:
    """Corner UVs by projecting onto two axes, normalised to [0, 1]."""
    p = m.vertices[:, list(axes)]
    lo, hi = p.min(0), p.max(0)
    uv = (p - lo) / np.where(hi > lo, hi - lo, 1.0)
    return uv[m.faces]


def box_uvs(m: mg.Mesh) -> np.ndarray:
    """UVs for a 12-triangle box: each face in its own cell of a 3 x 2 grid."""
    uvs = np.zeros((12, 3, 2))
    for f in range(6):
        tri = m.vertices[m.faces[2 * f:2 * f + 2]]                      # (2, 3, 3)
        n = np.cross(tri[0, 1] - tri[0, 0], tri[0, 2] - tri[0, 0])
        ax = [a for a in range(3) if abs(n[a]) < 1e-9][:2]
        p = tri[..., ax]
        lo, hi = p.reshape(-1, 2).min(0), p.reshape(-1, 2).max(0)
        local = (p - lo) / np.where(hi > lo, hi - lo, 1.0)
        cell = np.array([f % 3, f // 3], float)
        uvs[2 * f:2 * f + 2] = (cell + 0.05 + 0.9 * local) / np.array([3.0, 2.0])
    return uvs


def scene_from(objects, resolution=64) -> Scene:
    """objects: list of (name, Mesh, uvs (F, 3, 2)); one texture set per object."""
    pos, nrm, uv, sid = [], [], [], []
    for i, (name, m, u) in enumerate(objects):
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
    return scene_from([("floor", f, planar_uvs(f)), ("box", b, box_uvs(b))], res)
