"""Benchmark scenes modelled on the paper's table, built without Blender.

* room   (~21K tris): floor and three walls of two triangles each (minimal
  tessellation), a table, rug, two chairs, a shelf, spot the cow, a sphere, a
  torus, a vase and a lamp. Open front and top so the environment gets in.
* bunny-subdivided etc. for the triangle-count scaling table.

Scenes are unwrapped with xatlas and cached as job files in ``.cache/bench``
(the unwrap is not part of the bake's timing).
"""
from __future__ import annotations

import hashlib
import math
import os

import numpy as np

from ...core.io.jobfile import load_scene, save_scene
from ...core.model.scene import Scene
from . import meshgen as mg

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))
CACHE = os.path.join(ROOT, ".cache", "bench")


def room_objects() -> list[tuple[str, mg.Mesh]]:
    objs = [
        ("floor", mg.plane(6.0)),
        ("wall_back", wall((0, 3.0, 1.5), (6.0, 3.0), facing=(0, -1, 0))),
        ("wall_left", wall((-3.0, 0, 1.5), (6.0, 3.0), facing=(1, 0, 0))),
        ("wall_right", wall((3.0, 0, 1.5), (6.0, 3.0), facing=(-1, 0, 0))),
        ("rug", mg.box((2.4, 1.6, 0.01), (0.0, -0.2, 0.005))),
    ]
    table = [mg.box((1.6, 0.9, 0.05), (0, 0, 0.745))]
    for sx in (-0.72, 0.72):
        for sy in (-0.38, 0.38):
            table.append(mg.box((0.05, 0.05, 0.72), (sx, sy, 0.36)))
    objs.append(("table", mg.merge(table)))
    for i, (x, rot) in enumerate(((-1.2, 0.0), (1.2, math.pi))):
        parts = [mg.box((0.45, 0.45, 0.04), (0, 0, 0.45)), mg.box((0.04, 0.45, 0.5), (-0.2, 0, 0.72))]
        for sx in (-0.2, 0.2):
            for sy in (-0.2, 0.2):
                parts.append(mg.box((0.04, 0.04, 0.43), (sx, sy, 0.215)))
        objs.append((f"chair{i}", mg.merge(parts).transformed(rotate_z=rot, translate=(x, 0, 0))))
    shelf = [mg.box((1.2, 0.3, 0.03), (0, 0, z)) for z in (0.02, 0.5, 1.0, 1.5)]
    shelf += [mg.box((0.03, 0.3, 1.52), (x, 0, 0.76)) for x in (-0.6, 0.6)]
    shelf += [mg.box((0.2, 0.22, 0.3), (-0.3 + 0.25 * k, 0, 0.68)) for k in range(2)]
    objs.append(("shelf", mg.merge(shelf).transformed(translate=(-1.8, 2.8, 0))))
    spot = mg.load_obj(mg.asset_path("spot.obj"))
    spot.uvs = None
    # spot's model space is Y up; turn it Z up ((x, y, z) -> (x, -z, y), a proper
    # rotation, so the winding stays) and stand it on the table.
    spot.vertices = spot.vertices[:, [0, 2, 1]] * np.array([1, -1, 1])
    spot.normals = spot.normals[:, [0, 2, 1]] * np.array([1, -1, 1])
    zmin = spot.vertices[:, 2].min()
    objs.append(("spot", spot.transformed(scale=0.45, translate=(0.2, 0.1, 0.77 - 0.45 * zmin))))
    objs.append(("sphere", mg.uv_sphere(0.3, 64, 48).transformed(translate=(1.6, -1.0, 0.3))))
    objs.append(("torus", mg.torus(0.35, 0.1, 64, 32).transformed(translate=(-1.5, -1.2, 0.1))))
    prof = np.array([[0.001, 0.0], *[[0.12 + 0.08 * math.sin(math.pi * t), 0.5 * t] for t in np.linspace(0.0, 1.0, 22)],
                     [0.001, 0.5]])
    objs.append(("vase", mg.lathe(prof, 64).transformed(translate=(-0.5, 0.2, 0.77))))
    lp = np.array([[0.001, 0.0], [0.15, 0.0], [0.15, 0.03], [0.02, 0.05], [0.02, 1.4], [0.25, 1.45],
                   [0.12, 1.7], [0.001, 1.72]])
    objs.append(("lamp", mg.lathe(lp, 128).transformed(translate=(2.3, 2.3, 0.0))))
    return objs


def wall(center, size, facing) -> mg.Mesh:
    """A 2-triangle wall of (width, height) centred at ``center`` facing ``facing``."""
    p = mg.plane(size[0], size[1])
    f = np.asarray(facing, float)
    # plane faces +Z; map its local (x, y, z) to (tangent, up, facing)
    up = np.array([0.0, 0.0, 1.0])
    t = np.cross(up, f)
    M = np.stack([t, up, f], axis=1)
    v = p.vertices @ M.T + np.asarray(center, float)
    return mg.Mesh(v, p.faces)


def triangle_scaling_scene(target: int, resolution: int = 1024) -> Scene:
    """The room (same atlas, same texels) plus copies of the 69K-triangle bunny
    to reach about ``target`` triangles: bake time vs. triangles with
    everything else fixed. The bunnies cast shadows but get no texels
    (set_id -1), so no unwrap of a million triangles is needed."""
    room = room_scene(resolution, atlas=True)
    extra = target - room.n_triangles
    if extra <= 0:
        return room
    b = mg.load_obj(mg.asset_path("stanford-bunny.obj"), smooth=False)
    copies = max(1, int(round(extra / b.n_faces)))
    s = 1.2 / (b.vertices.max(0) - b.vertices.min(0)).max()
    tris = []
    for k in range(copies):
        m = b.transformed(scale=s)
        off = np.array([-2.4 + 0.8 * (k % 7), 2.2 - 0.8 * (k // 7), 0.0]) - [
            m.vertices[:, 0].mean(), m.vertices[:, 1].mean(), m.vertices[:, 2].min()]
        tris.append(m.corner_positions() + off)
    P = np.concatenate(tris)
    T = P.shape[0]
    fn = np.cross(P[:, 1] - P[:, 0], P[:, 2] - P[:, 0])
    fn /= np.maximum(np.linalg.norm(fn, axis=1, keepdims=True), 1e-300)
    return Scene(positions=np.concatenate([room.positions, P]),
                 normals=np.concatenate([room.normals, np.repeat(fn[:, None], 3, 1).astype(np.float32)]),
                 uvs=np.concatenate([room.uvs, np.zeros((T, 3, 2))]),
                 set_id=np.concatenate([room.set_id, np.full(T, -1, np.int32)]),
                 set_names=room.set_names, set_resolution=room.set_resolution,
                 object_id=np.concatenate([room.object_id, np.full(T, len(room.object_names), np.int32)]),
                 object_names=room.object_names + ["bunnies"])


def layout_code() -> str:
    """A digest of the code that makes the cached layouts (core's unwrap and
    meshgen): part of every cache key, so an edit there makes the scenes
    again instead of loading layouts the code no longer makes (a cache keyed
    by name alone hid issue 53's unwrap change from this machine's tests)."""
    from ...core.texels import unwrap
    h = hashlib.sha256()
    for mod in (unwrap, mg):
        with open(mod.__file__, "rb") as f:
            h.update(f.read())
    return h.hexdigest()[:8]


def cached_scene(name: str, builder, *, resolution: int, atlas: bool) -> Scene:
    """Build (or load from .cache/bench) a scene job unwrapped at ``resolution``."""
    key = hashlib.sha256(f"{name}-{resolution}-{atlas}-v2-{layout_code()}".encode()).hexdigest()[:12]
    path = os.path.join(CACHE, f"{name}-{resolution}-{'atlas' if atlas else 'sets'}-{key}.npz")
    if os.path.isfile(path):
        return load_scene(path)[0]
    sc = mg.assemble(builder(), resolution=resolution, atlas=atlas)
    os.makedirs(CACHE, exist_ok=True)
    save_scene(sc, path)
    return sc


def room_scene(resolution: int = 1024, atlas: bool = True, *, materials: bool = False) -> Scene:
    sc = cached_scene("room", room_objects, resolution=resolution, atlas=atlas)
    return with_room_materials(sc) if materials else sc


#: Principled-style materials of the room, by object (glossy floor and table,
#: diffuse walls and rug, a metal sphere, ...).
ROOM_MATERIALS = {
    "floor": {"base_color": [0.45, 0.30, 0.18], "roughness": 0.35},
    "wall_back": {"base_color": [0.80, 0.78, 0.72], "roughness": 0.9, "specular": 0.2},
    "wall_left": {"base_color": [0.80, 0.78, 0.72], "roughness": 0.9, "specular": 0.2},
    "wall_right": {"base_color": [0.80, 0.78, 0.72], "roughness": 0.9, "specular": 0.2},
    "rug": {"base_color": [0.60, 0.10, 0.08], "roughness": 1.0, "specular": 0.0},
    "table": {"base_color": [0.30, 0.18, 0.10], "roughness": 0.25},
    "sphere": {"base_color": [0.90, 0.85, 0.70], "metallic": 1.0, "roughness": 0.2},
    "torus": {"base_color": [0.10, 0.30, 0.70], "roughness": 0.4},
    "spot": {"base_color": [0.85, 0.85, 0.85], "roughness": 0.5},
    "vase": {"base_color": [0.20, 0.55, 0.35], "roughness": 0.15},
    "lamp": {"base_color": [0.10, 0.10, 0.10], "metallic": 1.0, "roughness": 0.3},
}


def warm_up(folder: str, settings, light=None) -> None:
    """Bake a toy room (64² atlas, the room's materials) with ``settings`` into
    ``folder``: a process's first bake pays its set-up (numba and its cached
    kernels, ray tables per ray count: ~1-2 s), which a timed bake that
    follows then does not. The benches that compare bake times call it first."""
    from ...core.bake.pipeline.runner import bake_scene  # the benches' scenes need not import the bake
    bake_scene(room_scene(64, atlas=True, materials=True), folder, settings, light=light, skip_if_unchanged=False)


def with_room_materials(sc: Scene) -> Scene:
    """The room scene with one Principled-style material per object."""
    from ...core.model.scene import validate
    names = sc.object_names
    sc.materials = [dict(name=n, **ROOM_MATERIALS.get(n, {"base_color": [0.6, 0.6, 0.6], "roughness": 0.5}))
                    for n in names]
    sc.material_id = sc.object_id.copy()
    validate(sc)
    return sc


def bunny_unwrapped(resolution: int = 256):
    """The 69K-triangle bunny (smooth, Z up, 0.5 m tall) and an xatlas unwrap,
    cached (the unwrap takes ~15 s)."""
    path = os.path.join(CACHE, f"bunny-uv-{resolution}-{layout_code()}.npz")
    b = mg.load_obj(mg.asset_path("stanford-bunny.obj"), smooth=True)
    # The scan is Y up: turn it Z up, scale to 0.5 m, stand it at the origin.
    v = b.vertices[:, [0, 2, 1]] * np.array([1.0, -1.0, 1.0])
    n = b.normals[:, [0, 2, 1]] * np.array([1.0, -1.0, 1.0]) if b.normals is not None else None
    b = mg.Mesh(v, b.faces, n)               # (x, y, z) -> (x, -z, y) is a rotation: winding kept
    s = 0.5 / (b.vertices[:, 2].max() - b.vertices[:, 2].min())
    c = b.vertices.mean(axis=0)
    b = b.transformed(scale=s, translate=(-c[0] * s, -c[1] * s, -b.vertices[:, 2].min() * s))
    if os.path.isfile(path):
        with np.load(path) as z:
            return b, np.array(z["uv"])
    from ...core.texels.unwrap import unwrap
    uv = unwrap([(b.vertices, b.faces)], resolution, padding=mg.chart_gap(2))[0]
    os.makedirs(CACHE, exist_ok=True)
    np.savez(path, uv=uv)
    return b, uv


def render_scaling_scene(bunnies: int, *, resolution: int = 1024, bunny_resolution: int = 256) -> Scene:
    """The room (one atlas) plus ``bunnies`` copies of the 69K-triangle bunny,
    each with its own 256^2 texture set (the copies share one unwrap, each gets
    its own texels): 21K, ~300K (4 copies), ~1.27M (18 copies) triangles, all drawn."""
    room = room_scene(resolution, atlas=True)
    if bunnies == 0:
        return room
    b, uv = bunny_unwrapped(bunny_resolution)
    P0, N0 = b.corner_positions(), b.corner_normals()
    pos, nrm, uvs = [room.positions], [room.normals], [room.uvs]
    set_id, obj_id = [room.set_id], [room.object_id]
    names, res, objs = list(room.set_names), [list(r) for r in room.set_resolution], list(room.object_names)
    for k in range(bunnies):
        x, y = -2.5 + (k % 6) * 1.0, -2.6 + (k // 6) * 0.9
        pos.append(P0 + [x, y, 0.0])
        nrm.append(N0)
        uvs.append(uv)
        set_id.append(np.full(b.n_faces, len(names), np.int32))
        obj_id.append(np.full(b.n_faces, len(objs), np.int32))
        names.append(f"bunny{k}")
        objs.append(f"bunny{k}")
        res.append([bunny_resolution, bunny_resolution])
    return Scene(positions=np.concatenate(pos), normals=np.concatenate(nrm).astype(np.float32),
                 uvs=np.concatenate(uvs), set_id=np.concatenate(set_id), set_names=names,
                 set_resolution=np.array(res), object_id=np.concatenate(obj_id), object_names=objs)


# --- the paper's four scene classes ------------------------------------------------------

def _y_up_to_z_up(m: mg.Mesh) -> mg.Mesh:
    """(x, y, z) -> (x, -z, y): a proper rotation, winding kept."""
    R = np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]])
    return mg.Mesh(m.vertices @ R.T, m.faces, None if m.normals is None else m.normals @ R.T, m.uvs)


def _standing(m: mg.Mesh, height: float, at=(0.0, 0.0)) -> mg.Mesh:
    """Scaled to ``height`` (metres, Z up) and stood on z = 0 at ``at``."""
    lo, hi = m.vertices.min(axis=0), m.vertices.max(axis=0)
    s = height / (hi[2] - lo[2])
    c = 0.5 * (lo + hi)
    return m.transformed(scale=s, translate=(at[0] - c[0] * s, at[1] - c[1] * s, -lo[2] * s))


def unwrapped_asset(name: str, resolution: int, *, y_up: bool) -> mg.Mesh:
    """A test model, Z up, with an xatlas unwrap (cached in .cache/bench: a
    100K-triangle model takes ~20 s)."""
    m = mg.load_obj(mg.asset_path(name), smooth=True)
    m.uvs = None
    if y_up:
        m = _y_up_to_z_up(m)
    path = os.path.join(CACHE, f"uv-{os.path.splitext(name)[0]}-{resolution}-{layout_code()}.npz")
    if os.path.isfile(path):
        with np.load(path) as z:
            m.uvs = np.array(z["uv"])
        return m
    from ...core.texels.unwrap import unwrap
    m.uvs = unwrap([(m.vertices, m.faces)], resolution, padding=mg.chart_gap(2))[0]
    os.makedirs(CACHE, exist_ok=True)
    np.savez(path, uv=m.uvs)
    return m


def _leaf(base, azimuth, elevation, length, width, droop, segments=12) -> mg.Mesh:
    """A thin curved leaf: a strip of 2 * segments triangles, one sheet."""
    t = np.linspace(0.0, 1.0, segments + 1)
    d = np.array([math.cos(elevation) * math.cos(azimuth), math.cos(elevation) * math.sin(azimuth),
                  math.sin(elevation)])
    side = np.array([-math.sin(azimuth), math.cos(azimuth), 0.0])
    centre = base + np.outer(t * length, d) - np.outer(droop * length * t ** 2, [0, 0, 1.0])
    half = 0.5 * width * np.sin(np.pi * np.clip(t, 0.02, 0.98))[:, None]
    fold = 0.15 * half * np.array([0, 0, 1.0])
    v = np.concatenate([centre - half * side + fold, centre + half * side + fold])
    n1 = segments + 1
    i = np.arange(segments)
    f = np.concatenate([np.stack([i, i + 1, n1 + i + 1], 1), np.stack([i, n1 + i + 1, n1 + i], 1)])
    m = mg.Mesh(v, f)
    m.normals = mg.vertex_normals(m)
    return m


def plants_objects(seed: int = 11) -> list[tuple[str, mg.Mesh]]:
    """Plants-class (~18K triangles): four potted plants of thin curved leaves
    on a 2-triangle floor in front of a 2-triangle wall."""
    rng = np.random.default_rng(seed)
    objs = [("floor", mg.plane(5.0)), ("wall", wall((0, 1.6, 1.25), (5.0, 2.5), facing=(0, -1, 0)))]
    pot_profile = np.array([[0.001, 0.0], [0.16, 0.0], [0.2, 0.32], [0.22, 0.34], [0.19, 0.34],
                            [0.16, 0.05], [0.001, 0.05]])
    for k, (x, y) in enumerate(((-1.4, 0.4), (-0.45, -0.2), (0.5, 0.35), (1.45, -0.25))):
        objs.append((f"pot{k}", mg.lathe(pot_profile, 48).transformed(translate=(x, y, 0.0))))
        leaves = []
        for _ in range(152):
            h = 0.3 + 0.9 * rng.random()
            base = np.array([x, y, h]) + 0.02 * rng.normal(size=3)
            leaves.append(_leaf(base, rng.uniform(0, 2 * np.pi), rng.uniform(0.1, 0.9), rng.uniform(0.2, 0.4),
                                rng.uniform(0.05, 0.09), rng.uniform(0.2, 0.7)))
        stem = mg.lathe(np.array([[0.001, 0.0], [0.015, 0.0], [0.012, 1.25], [0.001, 1.27]]), 16)
        objs.append((f"plant{k}", mg.merge(leaves + [stem.transformed(translate=(x, y, 0.3))])))
    return objs


def trm_objects() -> list[tuple[str, mg.Mesh]]:
    """Two-statues-and-a-monkey class (~458K triangles): two copies of the
    Nefertiti scan, the ogre head (our 'monkey'), the beast and the bunny on a
    2-triangle floor. Every model keeps its own unwrap (copies share theirs)."""
    nef = unwrapped_asset("nefertiti.obj", 1024, y_up=False)
    ogre = unwrapped_asset("ogre.obj", 1024, y_up=True)
    beast = unwrapped_asset("beast.obj", 512, y_up=True)
    bunny, uv = bunny_unwrapped(256)
    bunny.uvs = uv
    return [("floor", mg.plane(8.0)),
            ("statue_a", _standing(nef, 1.6, (-1.3, 0.3))), ("statue_b", _standing(nef, 1.6, (1.3, 0.3))),
            ("monkey", _standing(ogre, 0.7, (0.0, -0.6))), ("beast", _standing(beast, 0.6, (0.0, 0.9))),
            ("bunny", _standing(bunny, 0.45, (-0.9, -1.1)))]


def dragon_objects() -> list[tuple[str, mg.Mesh]]:
    """Dragon-class (~1.33M triangles): the bunny subdivided twice (1.11M
    triangles, its unwrap carried through the subdivision), the Nefertiti scan
    and the ogre head on a 2-triangle floor."""
    bunny, uv = bunny_unwrapped(1024)
    bunny.uvs = uv
    dense = mg.subdivide(mg.subdivide(bunny))
    nef = unwrapped_asset("nefertiti.obj", 1024, y_up=False)
    ogre = unwrapped_asset("ogre.obj", 1024, y_up=True)
    return [("floor", mg.plane(6.0)), ("dragon", _standing(dense, 1.2, (0.0, 0.0))),
            ("statue", _standing(nef, 1.2, (1.6, 0.6))), ("monkey", _standing(ogre, 0.6, (-1.5, 0.4)))]


#: name -> (builder, per-object sets?, default resolution)
PAPER_SCENES = {
    "room": (room_objects, True),
    "plants": (plants_objects, True),
    "trm": (trm_objects, False),
    "dragon": (dragon_objects, False),
}


def paper_scene(name: str, resolution: int = 1024) -> Scene:
    """One of the paper's scene classes, unwrapped (cached): room and plants in
    one atlas, trm and dragon with a set per object (floor at ``resolution``,
    models at half of it)."""
    builder, atlas = PAPER_SCENES[name]
    if atlas:
        return cached_scene(name, builder, resolution=resolution, atlas=True)
    key = hashlib.sha256(f"{name}-{resolution}-v1-{layout_code()}".encode()).hexdigest()[:12]
    path = os.path.join(CACHE, f"{name}-{resolution}-sets-{key}.npz")
    if os.path.isfile(path):
        return load_scene(path)[0]
    objs = builder()
    res = {n: (resolution if n == "floor" else max(64, resolution // 2)) for n, _ in objs}
    sc = mg.assemble(objs, resolution=resolution, keep_uvs=True, resolutions=res)
    os.makedirs(CACHE, exist_ok=True)
    save_scene(sc, path)
    return sc
