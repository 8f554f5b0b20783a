"""A room lit only through a window (issue 53, item 1): the transfer's noise,
measured against its converged value, raw and denoised.

A closed 4 x 4 x 2.6 m room of 0.2 m thick walls, floor and ceiling (boxes:
no gaps for light to leak through), one 1.2 x 1.2 m window in its +y wall
(sill 0.9 m), lit only by the environment (``env``) through that window; one
atlas for all of it (xatlas), no bounce. Inside, most of a texel's rays end on
the walls: its transfer is the few that leave through the window, the hard
case for a fixed ray count (docs/benchmarks.md, "A window-lit room").

Error: the irradiance of the environment's light (its dot product with the
transfer, mean over RGB) at each texel of the room's inner surfaces, against
the same texel's transfer traced with ``ref_rays`` rays (the cosine
estimator, without guided rays, so that the guided bake is not measured
against itself; at the bake's sample point: what is measured is the noise
and what a denoiser adds), over ``ref_texels`` texels
drawn at random from the inner surfaces: mean and 99th percentile of the
relative error |E - E_ref| / E_ref over the texels the window lights
(E_ref at least LIT of the room's mean), and over every picked texel the mean
absolute error relative to the mean irradiance ("nmae").
"""
from __future__ import annotations

import argparse
import os
import tempfile
import time

import numpy as np

from . import meshgen as mg

#: The room's inside (x, y, z extents from (-X/2, -Y/2, 0)), the walls' thickness and the window
#: (width, height, sill) centred in the +y wall.
ROOM = (4.0, 4.0, 2.6)
WALL = 0.2
WINDOW = (1.2, 1.2, 0.9)


def _slab(lo, hi) -> mg.Mesh:
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    return mg.box(tuple(hi - lo), tuple((hi + lo) / 2))


def build(resolution: int):
    """The core scene: floor, ceiling and walls as boxes, in one atlas of ``resolution``²."""
    from ...core.model.scene import validate
    X, Y, Z = ROOM[0] / 2, ROOM[1] / 2, ROOM[2]
    w = WALL
    ww, wh, sill = WINDOW
    parts = [
        ("floor", _slab((-X - w, -Y - w, -w), (X + w, Y + w, 0.0))),
        ("ceiling", _slab((-X - w, -Y - w, Z), (X + w, Y + w, Z + w))),
        ("wall_west", _slab((-X - w, -Y, 0.0), (-X, Y, Z))),
        ("wall_east", _slab((X, -Y, 0.0), (X + w, Y, Z))),
        ("wall_south", _slab((-X - w, -Y - w, 0.0), (X + w, -Y, Z))),
        # The +y wall around its window.
        ("wall_north_left", _slab((-X - w, Y, 0.0), (-ww / 2, Y + w, Z))),
        ("wall_north_right", _slab((ww / 2, Y, 0.0), (X + w, Y + w, Z))),
        ("wall_north_sill", _slab((-ww / 2, Y, 0.0), (ww / 2, Y + w, sill))),
        ("wall_north_head", _slab((-ww / 2, Y, sill + wh), (ww / 2, Y + w, Z))),
    ]
    sc = mg.assemble(parts, resolution=resolution, atlas=True)
    sc.materials = [dict(name="plaster", base_color=[0.7, 0.7, 0.7], roughness=0.8)]
    sc.material_id = np.zeros_like(sc.object_id)
    validate(sc)
    return sc


def inner_texels(gb) -> np.ndarray:
    """Indices (into the G-buffer's texels) of texels on the room's inner
    surfaces: inside its box (1 mm slack) with the normal pointing in."""
    X, Y, Z = ROOM[0] / 2, ROOM[1] / 2, ROOM[2]
    p, n = gb.position, gb.normal
    e = 1e-3
    inside = (np.abs(p[:, 0]) <= X + e) & (np.abs(p[:, 1]) <= Y + e) & (p[:, 2] >= -e) & (p[:, 2] <= Z + e)
    centre = np.array([0.0, 0.0, Z / 2])
    inward = np.einsum("ij,ij->i", n, centre - p) > 0
    return np.flatnonzero(inside & inward)


def reference(sc, gb, picked: np.ndarray, light: np.ndarray, ref_rays: int) -> np.ndarray:
    """(len(picked),) irradiance of ``light`` at the picked texels, traced with ``ref_rays`` rays."""
    from ...core.bake.estimators.raytrace import RayScene
    from ...core.bake.estimators.transfer import Points, TransferSettings, bake_points
    pts = Points(gb.position[picked], gb.normal[picked], gb.geo_normal[picked],
                 np.arange(picked.size, dtype=np.int64), np.zeros(picked.size, bool))
    T, _ = bake_points(RayScene(np.asarray(sc.positions, np.float64)), pts,
                       TransferSettings(bands=5, rays=ref_rays, seed=7, analytic=False, guiding=False))
    return (T.astype(np.float64) @ light).mean(axis=1)


#: Texels whose reference irradiance is below this fraction of the room's mean are left out of
#: the relative error (no light reaches them but SH ringing: their relative error is meaningless).
LIT = 0.1


def errors(E: np.ndarray, E_ref: np.ndarray) -> dict:
    """Mean and 99th percentile of |E - E_ref| / E_ref over the lit texels
    (E_ref >= LIT x the mean), and the mean of |E - E_ref| over all texels
    relative to the mean E_ref ("nmae")."""
    ok = E_ref >= LIT * E_ref.mean()
    rel = np.abs(E[ok] - E_ref[ok]) / E_ref[ok]
    return {"mean": float(rel.mean()), "p99": float(np.percentile(rel, 99)), "texels": int(ok.sum()),
            "nmae": float(np.abs(E - E_ref).mean() / E_ref.mean())}


def measure(resolution: int = 256, *, rays=(256,), ref_rays: int = 8192, ref_texels: int = 3000,
            env: str = "forest", denoisers=("none",), seed: int = 3, guiding=(True,),
            settings: dict | None = None, variants=None) -> dict:
    """Bake the room at each of ``rays``, with and without ``guiding``
    (estimators/guided.py), each with ``settings`` (BakeSettings fields), or
    instead with each of ``variants`` (dicts of BakeSettings fields, guiding
    included: bakes that differ in more than guiding against one reference),
    and filter it with each of ``denoisers`` (estimators.denoise: "none",
    "edge-aware", "oidn"); returns {"rows": [{rays, guiding, denoiser, mean,
    p99, bake_s, denoise_s}], ...}."""
    from ...core.bake.estimators import denoise
    from ...core.bake.pipeline.context import BakeSettings
    from ...core.bake.pipeline.runner import bake_scene
    from ...core.io.exr_io import read_sh_exr
    from ...core.light.envmap import environment_light
    from ...core.texels.gbuffer import build_gbuffer
    from ...core.texels.islands import island_labels

    sc = build(resolution)
    light = environment_light(env, 5)
    gb = build_gbuffer(sc, 0)
    inner = inner_texels(gb)
    rng = np.random.default_rng(seed)
    picked = np.sort(rng.choice(inner, size=min(ref_texels, inner.size), replace=False))
    t = time.perf_counter()
    E_ref = reference(sc, gb, picked, light, ref_rays)
    ref_s = time.perf_counter() - t
    H, W = gb.height, gb.width
    mask = gb.mask()
    pos = np.zeros((H * W, 3))
    nrm = np.zeros((H * W, 3))
    pos[gb.texel], nrm[gb.texel] = gb.position, gb.normal
    pos, nrm = pos.reshape(H, W, 3), nrm.reshape(H, W, 3)
    labels = island_labels(mask)
    both = mask[:, 1:] & mask[:, :-1]
    world_step = 2.0 * float(np.median(np.linalg.norm(pos[:, 1:] - pos[:, :-1], axis=-1)[both]))
    rows = []
    if variants is None:
        variants = [dict(settings or {}, guiding=g) for g in guiding]
    for r, kw in [(r, v) for r in rays for v in variants]:
        guide = kw.get("guiding", BakeSettings().guiding)
        with tempfile.TemporaryDirectory(prefix="prtt-window-room-") as d:
            t = time.perf_counter()
            bake_scene(sc, os.path.join(d, "b"), BakeSettings(rays=r, bounces=0, vertex_mode=False, **kw))
            bake_s = time.perf_counter() - t
            tex, _ = read_sh_exr(os.path.join(d, "b", "atlas.transfer.exr"))      # (H, W, K), row 0 at the bottom
        planes = np.ascontiguousarray(tex.transpose(2, 0, 1), np.float32)
        for name in denoisers:
            t = time.perf_counter()
            if name == "none":
                out = planes
            elif name == "oidn":
                out = denoise.oidn_sh(planes, mask, 5)
            elif name.startswith("edge-aware"):
                # edge-aware[:radius[:sigma in texels]]
                parts = name.split(":")
                radius = int(parts[1]) if len(parts) > 1 else 1
                sigma = float(parts[2]) if len(parts) > 2 else 1.0
                out = denoise.edge_aware(planes, mask, pos, nrm, radius=radius, sigma_texels=sigma,
                                         sigma_world=None if sigma == 1.0 else sigma * world_step, labels=labels)
            else:
                raise ValueError(f"unknown denoiser {name!r}")
            den_s = time.perf_counter() - t
            T = out.reshape(out.shape[0], -1)[:, gb.texel[picked]].T.astype(np.float64)
            E = (T @ light).mean(axis=1)
            rows.append(dict(rays=r, guiding=guide, denoiser=name, bake_s=round(bake_s, 2), denoise_s=round(den_s, 2),
                             **errors(E, E_ref)))
    return {"rows": rows, "resolution": resolution, "inner_texels": int(inner.size), "ref_rays": ref_rays,
            "ref_texels": int(picked.size), "ref_s": round(ref_s, 1), "env": env}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m prtt_addon.dev.bench window-room", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--resolution", type=int, default=256, help="the atlas's texels a side")
    p.add_argument("--rays", default="256", help="comma-separated rays per texel to bake with")
    p.add_argument("--ref-rays", type=int, default=8192)
    p.add_argument("--ref-texels", type=int, default=3000)
    p.add_argument("--denoise", default="none,edge-aware:1,edge-aware:2,oidn",
                   help="comma-separated filters (none, edge-aware[:radius[:sigma in texels]], oidn)")
    p.add_argument("--env", default="forest")
    p.add_argument("--guiding", default="on,off", help="comma-separated: on, off (rays aimed at the window or not)")
    p.add_argument("--texel-validity", action=argparse.BooleanOptionalAction, default=True,
                   help="bake with texel validity (the default) or without")
    p.add_argument("--guided-filter", action=argparse.BooleanOptionalAction, default=True,
                   help="smooth the guided texels (the default) or not")
    a = p.parse_args(argv)
    r = measure(a.resolution, rays=[int(x) for x in a.rays.split(",")], ref_rays=a.ref_rays,
                ref_texels=a.ref_texels, env=a.env, denoisers=a.denoise.split(","),
                guiding=[{"on": True, "off": False}[g] for g in a.guiding.split(",")],
                settings=dict(texel_validity=a.texel_validity, guided_filter=a.guided_filter))
    print(f"window room, {a.resolution}² atlas ({r['inner_texels']:,} inner texels), light {a.env}; reference "
          f"{r['ref_rays']} rays at {r['ref_texels']} texels ({r['ref_s']} s); texel validity "
          f"{'on' if a.texel_validity else 'off'}, guided filter {'on' if a.guided_filter else 'off'}")
    print(f"{'rays':>6} {'guiding':>7} {'denoiser':>14} {'mean':>8} {'p99':>8} {'nmae':>8} {'bake s':>7} {'denoise s':>9}")
    for x in r["rows"]:
        print(f"{x['rays']:>6} {'on' if x['guiding'] else 'off':>7} {x['denoiser']:>14} {x['mean']:>8.2%} {x['p99']:>8.2%} {x['nmae']:>8.2%} "
              f"{x['bake_s']:>7.2f} {x['denoise_s']:>9.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
