"""``python -m prtt_addon.dev.bench stress``: numerical stress cases, each checked.

Every case bakes a small scene through the real pipeline (core.bake.pipeline.runner.bake_scene:
G-buffer, Embree, projection, dilation, EXR) and checks its textures against
what must hold: finite values, the analytic transfer where it is known,
scale invariance, the documented bounds, and the warnings PRTT promises where
precision is lost. ``tests/test_stress.py`` runs the same cases.

Bounds used (docs/benchmarks.md):
* unoccluded texels: T = the clamped cosine turned to n, exactly (<= 1e-5,
  1e-3 relative in half storage) whatever the scale, thickness or overlaps;
* any texel: 0 <= T_0 <= sqrt(pi) / 2 (the unoccluded DC), up to half rounding;
* scale 1e-3 ... 1e4: the same texels as at scale 1 (same rays) within 2e-3;
* bounce DC terms >= 0; values beyond the half range (65504) are stored as
  float32 with a warning.
"""
from __future__ import annotations

import argparse
import math
import os
import tempfile

import numpy as np

from ...core.bake.estimators.transfer import unoccluded_transfer
from ...core.bake.pipeline.context import BakeSettings
from ...core.bake.pipeline.runner import bake_scene
from ...core.io.exr_io import read_sh_exr
from ...core.model.scene import Scene
from ...core.sh.basis import eval_basis
from . import meshgen as mg

T0_MAX = math.sqrt(math.pi) / 2.0            # DC of max(0, n.w) with nothing in the way


def _planar(m: mg.Mesh, axes=(0, 1), pad: float = 0.02) -> np.ndarray:
    p = m.vertices[:, list(axes)]
    lo, hi = p.min(0), p.max(0)
    uv = pad + (1 - 2 * pad) * (p - lo) / np.where(hi > lo, hi - lo, 1.0)
    return uv[m.faces]


def _scene(objects, res=32) -> Scene:
    """objects: (name, Mesh, uvs, normals or None); one set per object."""
    pos, nrm, uv, sid = [], [], [], []
    for i, (_, m, u, n) in enumerate(objects):
        pos.append(m.corner_positions())
        nrm.append(m.corner_normals() if n is None else n)
        uv.append(u)
        sid.append(np.full(m.n_faces, i))
    names = [o[0] for o in objects]
    return Scene(positions=np.concatenate(pos), normals=np.concatenate(nrm).astype(np.float32),
                 uvs=np.concatenate(uv), set_id=np.concatenate(sid), set_names=names,
                 set_resolution=np.array([[res, res]] * len(objects)),
                 object_id=np.concatenate(sid), object_names=names)


def floor_and_box(scale=1.0, subdiv=4):
    f = mg.plane(4.0, subdiv=subdiv).transformed(scale=scale)
    b = mg.box((1.0, 1.0, 1.0), (0, 0, 0.5)).transformed(scale=scale)
    return _scene([("floor", f, _planar(f), None), ("box", b, mg.box_face_uvs(b), None)])


def _bake(sc, d, **kw):
    kw.setdefault("rays", 64)
    kw.setdefault("bounces", 0)
    # No dilation: texels filled by dilation average neighbouring islands (by design), so
    # per-texel checks look at baked texels only. Dilation has its own tests.
    kw.setdefault("dilate", 0)
    m = bake_scene(sc, d, BakeSettings(**kw), skip_if_unchanged=False)
    # Sets with no covered texel (e.g. only zero-UV-area triangles) are skipped, with a warning.
    tex = {s["name"]: read_sh_exr(os.path.join(d, s["file"]))[0] for s in m["sets"] if not s.get("skipped")}
    return m, tex


def _covered(t):
    return np.any(t != 0, axis=-1)


def _check_common(tex, res, name):
    for n, t in tex.items():
        if not np.all(np.isfinite(t)):
            res["failures"].append(f"{name}: non-finite values in {n}")
        c = _covered(t)
        if c.any():
            t0 = t[c][:, 0]
            res["t0_min"] = min(res.get("t0_min", np.inf), float(t0.min()))
            res["t0_max"] = max(res.get("t0_max", -np.inf), float(t0.max()))
    if res.get("t0_min", 0) < -2e-3 or res.get("t0_max", 0) > T0_MAX * (1 + 1e-3) + 1e-4:
        res["failures"].append(f"{name}: T_0 outside [0, sqrt(pi)/2]: {res['t0_min']:.4g} .. {res['t0_max']:.4g}")


def _unoccluded_error(t, normal, bands):
    """Max |T - analytic| over covered texels of a set whose shading normal is ``normal``."""
    want = unoccluded_transfer(np.asarray([normal], float), bands)[0]
    c = _covered(t)
    return float(np.abs(t[c] - want).max())


# --- the cases --------------------------------------------------------------------------------

def case_scale(d):
    """Floor + box at 1e-3 ... 1e4 m: the same texels as at scale 1."""
    res = {"failures": []}
    base = None
    worst = 0.0
    for s in (1.0, 1e-3, 1e-1, 1e1, 1e4):
        _, tex = _bake(floor_and_box(scale=s), os.path.join(d, f"s{s:g}"), half=False)
        _check_common(tex, res, f"scale {s:g}")
        if base is None:
            base = tex
            continue
        worst = max(worst, max(float(np.abs(tex[n] - base[n]).max()) for n in tex))
    res["max_diff_vs_scale_1"] = worst
    if worst > 2e-3:
        res["failures"].append(f"transfer changes with scale by {worst:.3g} (> 2e-3)")
    return res


def clipped_cosine_transfer(tilt: float, bands: int, nodes: int = 256) -> np.ndarray:
    """Reference T_k = integral over w_z > 0 of max(0, n.w) y_k(w), n = (sin tilt, 0, cos tilt).

    What an unoccluded point with a smooth-shading normal tilted from its face
    normal (+Z) must get: rays below the face's horizon enter the surface.
    Independent of the bake: Gauss-Legendre in cos(theta) on [0, 1] times
    Gauss-Legendre in phi over the exact interval where n.w > 0, so both kinks
    of the integrand lie on interval ends and the rule converges spectrally.
    """
    x, w = np.polynomial.legendre.leggauss(nodes)
    mu, w_mu = 0.5 * (x + 1.0), 0.5 * w
    sa, ca = math.sin(tilt), math.cos(tilt)
    out = np.zeros(bands * bands)
    for m, wm in zip(mu, w_mu):
        s = math.sqrt(max(0.0, 1.0 - m * m))
        if sa * s <= 1e-300:
            continue
        c = -ca * m / (sa * s)                  # n.w > 0  <=>  cos(phi) > c
        if c >= 1.0:
            continue
        half = math.pi if c <= -1.0 else math.acos(c)
        phi, w_phi = half * x, half * w
        d = np.stack([s * np.cos(phi), s * np.sin(phi), np.full_like(phi, m)], axis=1)
        f = np.maximum(0.0, d @ np.array([sa, 0.0, ca]))
        out += wm * (w_phi * f) @ eval_basis(d, bands)
    return out


#: Grazing normals: sampling error bounds at 256 rays (measured max 0.03, mean |DC| 1e-4).
GRAZING_MAX_ERR = 0.06
GRAZING_MEAN_DC_ERR = 2e-3


def case_normals(d):
    """Grazing (89.9 deg from the face) and flipped shading normals on open planes.

    The grazing plane's texels must match the horizon-clipped clamped cosine
    (no bias: a grazing smooth normal is baked as it is, not bent); the
    flipped plane (shading normal -Z on a +Z face, nothing below) must get the
    exact unoccluded transfer about -Z.
    """
    res = {"failures": []}
    p = mg.plane(2.0, subdiv=2)
    tilt = math.radians(89.9)
    grazing = np.tile([math.sin(tilt), 0.0, math.cos(tilt)], (p.n_faces, 3, 1))
    flipped = np.tile([0.0, 0.0, -1.0], (p.n_faces, 3, 1))
    # The flipped plane sits below the grazing one: each is outside the other's hemisphere.
    sc = _scene([("grazing", p, _planar(p), grazing),
                 ("flipped", p.transformed(translate=(0, 0, -10)), _planar(p), flipped)])
    _, tex = _bake(sc, d, half=False, rays=256)
    _check_common(tex, res, "normals")
    t = tex["grazing"]
    c = _covered(t)
    want = clipped_cosine_transfer(tilt, 5)
    res["grazing_max_err"] = float(np.abs(t[c] - want).max())
    res["grazing_mean_dc_err"] = float(abs(np.mean(t[c][:, 0] - want[0])))
    res["flipped_vs_analytic"] = _unoccluded_error(tex["flipped"], flipped[0, 0], 5)
    for k, bound in (("grazing_max_err", GRAZING_MAX_ERR), ("grazing_mean_dc_err", GRAZING_MEAN_DC_ERR),
                     ("flipped_vs_analytic", 1e-5)):
        if res[k] > bound:
            res["failures"].append(f"{k} = {res[k]:.3g} (> {bound:g})")
    return res


def _axis_error(t):
    """Per covered texel: distance to the nearest of the six axis-aligned unoccluded transfers."""
    axes = np.concatenate([np.eye(3), -np.eye(3)])
    want = unoccluded_transfer(axes, int(round(math.sqrt(t.shape[-1]))))
    c = _covered(t)
    return np.abs(t[c][:, None, :] - want[None]).max(axis=2).min(axis=1)


def case_thin_and_coincident(d):
    """A 10 um thick slab, and two coincident quads: no acne, no leak, no z-fighting.

    Every face of the slab sees its whole hemisphere (the rest of the slab lies
    in the plane behind it), so every texel must get the exact unoccluded
    transfer about its face's axis; a texel that hits its own slab (acne from
    the opposite face 10 um away) would not. The coincident quads must not
    shadow each other.
    """
    res = {"failures": []}
    slab = mg.box((2.0, 2.0, 1e-5), (0.0, 0.0, 0.0))
    _, tex = _bake(_scene([("slab", slab, mg.box_face_uvs(slab), None)], res=48),
                   os.path.join(d, "slab"), half=False)
    _check_common(tex, res, "thin slab")
    res["slab_vs_analytic"] = float(_axis_error(tex["slab"]).max())
    quad = mg.plane(1.5, subdiv=1)
    _, tex = _bake(_scene([("quad", quad, _planar(quad), None), ("twin", quad, _planar(quad), None)], res=48),
                   os.path.join(d, "twins"), half=False)
    _check_common(tex, res, "coincident")
    res["coincident_vs_analytic"] = max(_unoccluded_error(tex["quad"], [0, 0, 1.0], 5),
                                        _unoccluded_error(tex["twin"], [0, 0, 1.0], 5))
    for k in ("slab_vs_analytic", "coincident_vs_analytic"):
        if res[k] > 1e-5:
            res["failures"].append(f"{k} = {res[k]:.3g} (> 1e-5)")
    return res


def case_degenerate(d):
    """Needle (aspect 1e6), zero-area 3D and zero-area UV triangles beside a normal floor."""
    res = {"failures": []}
    f = mg.plane(2.0, subdiv=2)
    needle = mg.Mesh(np.array([[0, 0, 0.5], [1.0, 0, 0.5], [0.5, 1e-6, 0.5]]), np.array([[0, 1, 2]]))
    point = mg.Mesh(np.array([[0.2, 0.2, 0.8]] * 3), np.array([[0, 1, 2]]))
    uv_line = mg.Mesh(np.array([[0, 0, 1.0], [1, 0, 1.0], [0, 1, 1.0]]), np.array([[0, 1, 2]]))
    sc = _scene([("floor", f, _planar(f), None),
                 ("needle", needle, np.array([[[0.1, 0.1], [0.9, 0.1], [0.5, 0.9]]]),
                  np.tile([0, 0, 1.0], (1, 3, 1))),
                 ("point", point, np.array([[[0.1, 0.1], [0.9, 0.1], [0.5, 0.9]]]),
                  np.tile([0, 0, 1.0], (1, 3, 1))),
                 ("uv_line", uv_line, np.array([[[0.1, 0.5], [0.5, 0.5], [0.9, 0.5]]]), None)], res=32)
    m, tex = _bake(sc, d, half=False)
    _check_common(tex, res, "degenerate")
    sets = {s["name"]: s for s in m["sets"]}
    res["zero_area_uv_triangles"] = sets["uv_line"]["zero_area_uv_triangles"]
    res["needle_texels"] = sets["needle"]["texels"]
    res["point_texels"] = sets["point"]["texels"]
    if not sets["uv_line"].get("skipped") or "uv_line" in tex:
        res["failures"].append("the set with only a zero-UV-area triangle was not skipped")
    if res["needle_texels"] == 0 or res["point_texels"] == 0:
        res["failures"].append("the needle / zero-area triangle lost its texels")
    if res["zero_area_uv_triangles"] != 1:
        res["failures"].append("the zero-area UV triangle was not reported")
    if not any("zero-area" in w or "no texels" in w for w in m["warnings"]):
        res["failures"].append(f"no warning about the zero-area UV triangle: {m['warnings']}")
    return res


def case_islands(d):
    """One island covering the whole texture, and 400 islands smaller than a texel."""
    res = {"failures": []}
    big = mg.plane(1.0, subdiv=1)
    big_uv = big.vertices[big.faces][..., :2] + 0.5                   # exactly [0, 1]^2
    rng = np.random.default_rng(0)
    tris, uvs = [], []
    for k in range(400):
        c = np.array([k % 20, k // 20], float) * 0.15 + 3.0
        tris.append(np.array([[c[0], c[1], 0], [c[0] + 0.05, c[1], 0], [c[0], c[1] + 0.05, 0]]))
        u = (np.array([k % 20, k // 20]) + 0.2 + 0.4 * rng.random(2)) / 20.0   # one per grid cell
        uvs.append(np.array([u, u + [0.3 / 64, 0], u + [0, 0.3 / 64]]))       # 0.3 texel wide
    tiny = mg.Mesh(np.concatenate(tris), np.arange(1200).reshape(400, 3))
    sc = _scene([("huge", big, big_uv, None), ("tiny", tiny, np.array(uvs), None)], res=64)
    m, tex = _bake(sc, d, half=False)
    _check_common(tex, res, "islands")
    res["huge_covered_fraction"] = float(_covered(tex["huge"]).mean())
    sets = {s["name"]: s for s in m["sets"]}
    res["tiny_texels"] = sets["tiny"]["texels"]
    if res["huge_covered_fraction"] < 0.99:
        res["failures"].append(f"the full-texture island covers {res['huge_covered_fraction']:.3f} of it")
    if res["tiny_texels"] < 400:
        res["failures"].append(f"400 sub-texel islands got only {res['tiny_texels']} texels")
    return res


def case_bands16(d):
    """16 bands (256 coefficients): finite, unoccluded texels exact, DC in bounds."""
    res = {"failures": []}
    _, tex = _bake(floor_and_box(), d, bands=16, rays=256, half=False)
    _check_common(tex, res, "16 bands")
    # The box's top sees nothing: those texels must hold the exact 16-band clamped cosine.
    t = tex["box"]
    want = unoccluded_transfer(np.array([[0, 0, 1.0]]), 16)[0]
    err = np.abs(t - want).max(axis=-1)
    top = _covered(t) & (err < 1e-3)
    res["box_top_texels"] = int(top.sum())
    res["box_top_vs_analytic"] = float(err[top].max()) if top.any() else float("inf")
    res["coefficients"] = int(t.shape[-1])
    if t.shape[-1] != 256 or top.sum() < 48 or res["box_top_vs_analytic"] > 1e-5:
        res["failures"].append("16-band bake lost its unoccluded texels")
    return res


def case_half_overflow_and_sun(d):
    """A one-pixel 1e9 sun: bounce values beyond the half range go to float32 with a warning.

    The pixel (64 x 128 equirect, ~2e-3 sr) carries ~2e6 times the energy of a
    unit sky, enough to push the one-bounce radiance past 65504.
    """
    from ...core.light.envmap import project_equirect
    res = {"failures": []}
    env = np.zeros((64, 128, 3), np.float32)
    env[10, 30] = 1.0e9                                    # one pixel, a tiny very bright sun
    light = project_equirect(env, 5)
    sc = floor_and_box()
    sc.materials = [{"name": "white", "base_color": [0.9, 0.9, 0.9], "roughness": 0.5}]
    sc.material_id = np.zeros(sc.n_triangles, np.int32)
    m = bake_scene(sc, d, BakeSettings(rays=64, bounces=1, bounce_rays=32, bounce_mode="baked"), light=light,
                   skip_if_unchanged=False)
    res["warnings"] = [w for w in m["warnings"] if "half" in w]
    b = m["bounce"]
    storages = {s["storage"] for s in b["sets"]}
    res["bounce_storage"] = sorted(storages)
    for s in b["sets"]:
        data, _ = read_sh_exr(os.path.join(d, s["file"]))
        if not np.all(np.isfinite(data)):
            res["failures"].append(f"{s['file']}: non-finite")
        res["bounce_dc_min"] = min(res.get("bounce_dc_min", np.inf), float(data[..., 0].min()))
        res["bounce_max"] = max(res.get("bounce_max", 0.0), float(np.abs(data).max()))
    if res["bounce_max"] > 65504 and ("float" not in storages or not res["warnings"]):
        res["failures"].append("values beyond the half range were not stored as float with a warning")
    if res["bounce_dc_min"] < -1e-6 * res["bounce_max"]:
        res["failures"].append(f"negative bounce DC {res['bounce_dc_min']:.3g}")
    return res


def case_rotation_range(d):
    """What tests/test_properties.py states, measured over many draws: SH
    rotation at 16 bands (the most a texture may hold) keeps every band's
    norm, composes, and the bake's float32 rotate_zyz stays within its bound,
    for coefficients from 1e-30 to 1e30."""
    from ...core.base.blas import single_threaded_blas
    with single_threaded_blas():      # 600 small products: BLAS threads only wait on each other
        return _rotation_range()


def _rotation_range():
    from ...core.sh.rotation import rotate_zyz, rotation_zyz, sh_rotation
    res = {"failures": []}
    rng = np.random.default_rng(36)
    n, draws, batch = 16, 300, 50
    ang = rng.uniform(-2 * np.pi, 2 * np.pi, (draws, 2, 3))
    norm_drift = compose = f32 = 0.0
    for b0 in range(0, draws, batch):
        a = ang[b0:b0 + batch]
        R1, R2 = rotation_zyz(*a[:, 0].T), rotation_zyz(*a[:, 1].T)
        D1, D2, D12 = sh_rotation(R1, n), sh_rotation(R2, n), sh_rotation(R1 @ R2, n)   # batched
        compose = max(compose, float(np.abs(D12 - D1 @ D2).max()))
        c = rng.standard_normal((len(a), n * n)) * 10.0 ** rng.integers(-30, 31, (len(a), 1))
        out = np.einsum("bij,bj->bi", D1, c)
        for l in range(n):
            sl = slice(l * l, (l + 1) ** 2)
            x, y = np.linalg.norm(c[:, sl], axis=1), np.linalg.norm(out[:, sl], axis=1)
            norm_drift = max(norm_drift, float((np.abs(x - y) / x).max()))
        u = rng.standard_normal((len(a), n * n))
        got = rotate_zyz(u.astype(np.float32), *a[:, 0].T)
        ref = np.einsum("bij,bj->bi", D1, u)
        f32 = max(f32, float((np.abs(got - ref).max(axis=1) / np.linalg.norm(u, axis=1)).max()))
    res["band_norm_drift"] = norm_drift
    res["composition_error"] = compose
    res["float32_rotation_error"] = f32
    res["float32_eps_units"] = f32 / float(np.finfo(np.float32).eps)
    if norm_drift > 1e-12 or compose > 1e-12 or f32 > 64 * n * np.finfo(np.float32).eps:
        res["failures"].append("SH rotation outside its stated bounds at 16 bands")
    return res


CASES = {
    "scale 1e-3 .. 1e4": case_scale,
    "grazing and flipped normals": case_normals,
    "thin shell, coincident faces": case_thin_and_coincident,
    "needle and degenerate triangles": case_degenerate,
    "huge and sub-texel UV islands": case_islands,
    "16 bands": case_bands16,
    "tiny 1e9 sun, half overflow": case_half_overflow_and_sun,
    "SH rotation, 16 bands, 1e-30..1e30": case_rotation_range,
}


def run_case(name: str, work_dir: str | None = None) -> dict:
    with tempfile.TemporaryDirectory(prefix="prtt-stress-") as tmp:
        return CASES[name](work_dir or tmp)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m prtt_addon.dev.bench stress", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.parse_args(argv)
    bad = 0
    for name in CASES:
        r = run_case(name)
        fails = r.pop("failures")
        bad += bool(fails)
        shown = ", ".join(f"{k}={v:.3g}" if isinstance(v, float) else f"{k}={v}" for k, v in r.items())
        print(f"{'FAIL' if fails else 'ok  '} {name:32s} {shown}")
        for f in fails:
            print(f"     {f}")
    print(f"{len(CASES) - bad}/{len(CASES)} cases hold")
    return 1 if bad else 0
