"""The bounce bake's precomputed exit radiance against a slow per-hit reference,
its determinism across thread counts, and the early stop of bounce levels."""
import dataclasses
import json
import math

import numpy as np
import pytest

from prtt_addon.core.bake.estimators import hit_kernel
from prtt_addon.core.bake.estimators.bounce import (
    ExitShader,
    IncidentSet,
    block_mean_incident,
    exit_textures,
    glossy_triangles,
    incident_at,
    incident_dc_at,
    level_energy,
    surface_texels,
)
from prtt_addon.core.bake.pipeline.context import BakeSettings
from prtt_addon.core.bake.pipeline.runner import bake_scene
from prtt_addon.core.base import jit
from prtt_addon.core.io import exr_io
from prtt_addon.core.sh.gaunt import tpfl_matrix
from prtt_addon.core.shading.materials import ShadingParams
from prtt_addon.core.shading.shade import outgoing
from prtt_addon.core.texels.gbuffer import build_gbuffer
from tests.test_bounce import corner_scene, sky

GLOSSY_WALL = {"name": "glossy", "base_color": [0.2, 0.3, 0.9], "roughness": 0.3, "specular": 1.0,
               "metallic": 0.5}
DIFFUSE_FLOOR = {"name": "floor", "base_color": [0.5, 0.4, 0.3], "specular": 0.0}


def _reference_radiance(sc, surf, T_pm, light, bands, tri, u, v, view, clamp=True):
    """Per hit, in float64, one hit at a time: the texel nearest to the hit's uv,
    that texel's transfer lit by the light through the triple-product matrix,
    and the reference shading model (shading.outgoing) with that texel's
    material and normal, the lobe only on triangles whose material has one."""
    K = bands * bands
    M = tpfl_matrix(np.asarray(light, np.float64)[:K], bands)          # (3, K, K)
    where = {int(t): i for i, t in enumerate(surf.valid)}
    glossy = glossy_triangles(sc)
    out = np.zeros((tri.size, 3))
    for h in range(tri.size):
        t = int(tri[h])
        b = np.array([1.0 - u[h] - v[h], u[h], v[h]])
        uv = b @ sc.uvs[t].astype(np.float64)
        ix = min(max(int(math.floor(uv[0] * surf.width)), 0), surf.width - 1)
        iy = min(max(int(math.floor(uv[1] * surf.height)), 0), surf.height - 1)
        i = where.get(iy * surf.width + ix)
        if i is None:
            continue                                    # an empty texel: nothing leaves
        T = T_pm[iy * surf.width + ix].astype(np.float64)
        Lp = np.einsum("cik,k->ci", M, T)[None]                         # (1, 3, K)
        spec = surf.spec[i:i + 1] if glossy[t] else np.zeros((1, 3))
        p = ShadingParams(surf.albedo[i:i + 1], spec, surf.exponent[i:i + 1])
        out[h] = outgoing(Lp, surf.normal[i:i + 1], view[h:h + 1].astype(np.float64), p, clamp=clamp, layered=False)[0]
    return out


def _shade(shader, path, tri, u, v, view):
    """(n, 3) radiance at hits by one of ExitShader's two paths: its numpy
    ``radiance`` or the compiled per-hit loop (hit_kernel) behind ``shade_rays``."""
    tri, u, v = tri.astype(np.int64), u.astype(np.float32), v.astype(np.float32)
    if path == "numpy":
        return shader.radiance(tri, u, v, view.astype(np.float32))
    assert hit_kernel.available(), "numba is a pinned dependency (requirements.txt)"
    shader.compiled = True
    assert shader.path() == "compiled", jit.failures          # not numpy against numpy
    # Every other ray a miss: rows the hits do not own must stay as they were.
    L = np.full((2 * tri.size, 3), -7.0, np.float32)
    D = np.zeros((2 * tri.size, 3), np.float32)
    rows = 2 * np.arange(tri.size)
    D[rows] = -view
    shader.shade_rays(L, tri, u, v, rows, D)
    assert np.all(L[1::2] == -7.0)
    return L[rows]


PATHS = ["numpy", "compiled"]


def _random_hits(sc, rng, n):
    """n hits anywhere on the scene: triangles, barycentrics (u, v) and unit view vectors."""
    tri = rng.integers(0, sc.n_triangles, n)
    u, v = rng.random(n), rng.random(n)
    flip = u + v > 1.0
    u[flip], v[flip] = 1.0 - u[flip], 1.0 - v[flip]
    view = rng.normal(size=(n, 3))
    view /= np.linalg.norm(view, axis=1, keepdims=True)
    return tri, u, v, view


@pytest.mark.parametrize("path", PATHS)
@pytest.mark.parametrize("wall", [GLOSSY_WALL, {"name": "diffuse", "base_color": [0.9, 0.6, 0.3],
                                                "specular": 0.0}])
def test_exit_radiance_equals_slow_per_hit_reference(wall, path):
    sc = corner_scene(wall, res=16)
    sc.materials[0] = DIFFUSE_FLOOR
    bands = 5
    light = sky(bands)
    rng = np.random.default_rng(3)
    exits, surfs, T_pms = {}, {}, {}
    for s in range(len(sc.set_names)):
        gb = build_gbuffer(sc, s)
        surf = surface_texels(sc, gb, 2)
        # A transfer texture with every texel different (a real bake's values
        # would hide indexing mistakes behind smooth data).
        T_pm = np.zeros((gb.width * gb.height, bands * bands), np.float32)
        T_pm[surf.valid] = rng.normal(0.5, 0.3, (surf.valid.size, bands * bands))
        Lp = incident_at(surf, IncidentSet.from_pixel_major(T_pm, gb.width, gb.height), light, bands)
        exits[s] = exit_textures(surf, Lp, bands)
        surfs[s], T_pms[s] = surf, T_pm
    shader = ExitShader(sc, exits, bands, glossy_triangles(sc))
    n = 400
    tri, u, v, view = _random_hits(sc, rng, n)
    got = _shade(shader, path, tri, u, v, view)
    ref = np.zeros((n, 3))
    for s in exits:
        sel = np.flatnonzero(sc.set_id[tri] == s)
        ref[sel] = _reference_radiance(sc, surfs[s], T_pms[s], light, bands, tri[sel], u[sel], v[sel], view[sel])
    assert np.count_nonzero(ref) > n                       # most hits see light
    scale = np.abs(ref).max()
    assert np.abs(got - ref).max() <= 2e-5 * scale, np.abs(got - ref).max() / scale
    wall_hits = np.flatnonzero(sc.set_id[tri] == 1)
    no_lobe = _shade(ExitShader(sc, exits, bands, np.zeros(sc.n_triangles, bool)), path, tri, u, v, view)
    lobe = np.abs(no_lobe[wall_hits] - got[wall_hits]).max()
    if wall is GLOSSY_WALL:
        assert lobe > 0.05 * scale               # the glossy path is exercised, and matches
    else:
        assert lobe == 0.0                       # no lobe row for a diffuse set


def test_block_mean_incident_is_the_mean_of_valid_texels():
    rng = np.random.default_rng(5)
    W, H, C, f = 12, 8, 4, 2
    pm = rng.normal(size=(W * H, C)).astype(np.float32)
    valid = np.flatnonzero(rng.random(W * H) < 0.6)
    got = block_mean_incident(IncidentSet.from_pixel_major(pm, W, H), valid, f, 3)
    assert (got.width, got.height) == (W // f, H // f)
    is_valid = np.zeros(W * H, bool)
    is_valid[valid] = True
    for by in range(H // f):
        for bx in range(W // f):
            idx = [(by * f + j) * W + bx * f + i for j in range(f) for i in range(f)]
            idx = [k for k in idx if is_valid[k]]
            if idx:
                np.testing.assert_allclose(got.band(0, got.height)[by * (W // f) + bx], pm[idx].astype(np.float64).mean(axis=0),
                                           rtol=1e-6, atol=1e-6)


@pytest.mark.parametrize("path", PATHS)
def test_diffuse_from_the_fine_grid_glossy_from_the_coarse_one(path):
    """Level 1 under tuning auto: per hit, the diffuse term of the fine grid's
    nearest texel plus the glossy lobe of the coarse grid's nearest texel lit
    by the block mean of the transfer (slow reference as above, per term)."""
    sc = corner_scene(GLOSSY_WALL, res=32)
    sc.materials[0] = DIFFUSE_FLOOR
    bands, f = 5, 2
    light = sky(bands)
    rng = np.random.default_rng(4)
    exits, parts = {}, {}
    for s in range(len(sc.set_names)):
        gb = build_gbuffer(sc, s)
        coarse = build_gbuffer(sc, s, resolution=(gb.width // f, gb.height // f))
        fine = surface_texels(sc, gb, 2, diffuse_only=True)
        assert not fine.glossy
        surf = surface_texels(sc, coarse, 2)
        T_pm = np.zeros((gb.width * gb.height, bands * bands), np.float32)
        T_pm[fine.valid] = rng.normal(0.5, 0.3, (fine.valid.size, bands * bands))
        inc = IncidentSet.from_pixel_major(T_pm, gb.width, gb.height)
        dc = incident_dc_at(fine, inc, light, bands)
        np.testing.assert_allclose(dc, incident_at(fine, inc, light, bands)[:, :, 0], rtol=1e-5, atol=1e-5)
        inc_c = block_mean_incident(inc, fine.valid, f, 2)
        exits[s] = exit_textures(surf, incident_at(surf, inc_c, light, bands), bands, diffuse_at=(fine, dc))
        parts[s] = (fine, T_pm, surf, inc_c.band(0, inc_c.height))
    glossy = glossy_triangles(sc)
    shader = ExitShader(sc, exits, bands, glossy)
    n = 400
    tri, u, v, view = _random_hits(sc, rng, n)
    got = _shade(shader, path, tri, u, v, view)
    ref = np.zeros((n, 3))
    for s, (fine, T_pm, surf, Tc_pm) in parts.items():
        sel = np.flatnonzero(sc.set_id[tri] == s)
        no_spec = dataclasses.replace(fine, spec=np.zeros_like(fine.spec))
        diffuse = _reference_radiance(sc, no_spec, T_pm, light, bands, tri[sel], u[sel], v[sel], view[sel],
                                       clamp=False)
        lobe_only = dataclasses.replace(surf, albedo=np.zeros_like(surf.albedo))
        lobe = _reference_radiance(sc, lobe_only, Tc_pm, light, bands, tri[sel], u[sel], v[sel], view[sel],
                                    clamp=False)
        ref[sel] = np.maximum(diffuse + lobe, 0.0)
    scale = np.abs(ref).max()
    assert np.abs(got - ref).max() <= 2e-5 * scale, np.abs(got - ref).max() / scale
    wall = np.flatnonzero(glossy[tri])
    assert wall.size and np.abs(ref[wall]).max() > 0.05 * scale


def test_bounce_textures_identical_for_any_thread_count(tmp_path):
    sc = corner_scene(GLOSSY_WALL, res=24)
    outs = []
    for threads in (1, 2, 3):
        d = tmp_path / f"t{threads}"
        bake_scene(sc, d, BakeSettings(rays=64, bounces=2, bounce_rays=32, threads=threads, half=False,
                                       bounce_tolerance=0.0, bounce_mode="baked"), light=sky())
        outs.append([(d / f"{n}.bounce{k}.exr") for n in ("floor", "wall") for k in (1, 2)])
    for files in outs[1:]:
        for a, b in zip(outs[0], files):
            da, _ = exr_io.read_sh_exr(a)
            db, _ = exr_io.read_sh_exr(b)
            assert np.array_equal(da, db), (a, b)


def test_levels_stop_early_below_the_tolerance_and_say_so(tmp_path):
    dark = {"name": "dark", "base_color": [0.05, 0.05, 0.05], "specular": 0.0}
    sc = corner_scene(dark, res=16)
    sc.materials[0] = {"name": "floor", "base_color": [0.05, 0.05, 0.05], "specular": 0.0}
    events = []
    m = bake_scene(sc, tmp_path / "stop", BakeSettings(rays=64, bounces=3, bounce_rays=32,
                                                       bounce_tolerance=0.01, bounce_mode="baked"),
                   light=sky(), progress=events.append)
    stop = m["bounce"]["stopped_early"]
    assert stop["after_level"] == 1 and stop["levels_not_baked"] == 2 and stop["energy_ratio"] < 0.01
    assert all(".bounce1." in f for f in m["bounce"]["files"])
    info = [e for e in events if e.get("type") == "info"]
    assert len(info) == 1 and "levels 2-3 are not baked" in info[0]["message"]
    json.dumps(m)                                         # the note is plain JSON
    # The ratio is the level's DC energy over the direct light's.
    data, _ = exr_io.read_sh_exr(tmp_path / "stop" / "wall.bounce1.exr")
    assert data[..., 0].sum() > 0
    # Tolerance 0 bakes every level.
    m0 = bake_scene(sc, tmp_path / "all", BakeSettings(rays=64, bounces=3, bounce_rays=32, bounce_tolerance=0.0,
                                                       bounce_mode="baked"),
                    light=sky())
    assert m0["bounce"]["stopped_early"] is None
    assert any(".bounce3." in f for f in m0["bounce"]["files"])


def test_level_energy_is_the_dc_sum():
    rows = np.zeros((4, 3, 9))
    rows[:, :, 0] = [[1, 2, 3]] * 4
    rows[:, :, 1] = 100.0                                  # higher bands carry no energy
    assert level_energy(rows) == pytest.approx(24.0)
    assert level_energy(rows.reshape(4, 27)) == pytest.approx(24.0)


@pytest.mark.parametrize("bands", [2, 3, 5, 7])
def test_compiled_and_numpy_paths_agree_on_many_hits_and_sets_without_exits(bands):
    """The compiled loop against the numpy path on 20,000 hits: the same texel
    per hit (identical float32 texture coordinates), so the results differ by
    float32 rounding of the sums only; hits on a set with no exit textures
    (dark this level) get zero on both paths. Band counts with a loop
    compiled for them (3, 5) and without (2, 7)."""
    sc = corner_scene(GLOSSY_WALL, res=32)
    light = sky(bands)
    rng = np.random.default_rng(11)
    exits = {}
    for s in range(len(sc.set_names)):
        gb = build_gbuffer(sc, s)
        surf = surface_texels(sc, gb, 2)
        T_pm = rng.normal(0.5, 0.3, (gb.width * gb.height, bands * bands)).astype(np.float32)
        exits[s] = exit_textures(surf, incident_at(surf, IncidentSet.from_pixel_major(T_pm, gb.width, gb.height), light, bands),
                                 bands)
    tri, u, v, view = _random_hits(sc, rng, 20000)
    for sets in (exits, {1: exits[1]}):
        shader = ExitShader(sc, sets, bands, glossy_triangles(sc))
        a = _shade(shader, "numpy", tri, u, v, view)
        b = _shade(shader, "compiled", tri, u, v, view)
        scale = np.abs(a).max()
        assert scale > 0
        assert np.abs(a - b).max() <= 1e-6 * scale, np.abs(a - b).max() / scale
        dark = np.flatnonzero(~np.isin(sc.set_id[tri], list(sets)))
        assert np.all(b[dark] == 0.0) and np.all(a[dark] == 0.0)


def test_numba_can_be_switched_off(tmp_path, monkeypatch):
    """PRTT_NO_NUMBA=1: numba is not even imported, and the bake shades with
    numpy (the manifest says so)."""
    import os
    import subprocess
    import sys
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    code = ("import sys; from prtt_addon.core.bake.estimators import hit_kernel; "
            "print(hit_kernel.available(), hit_kernel.usable('baked', 5), 'numba' in sys.modules)")
    for value, want in (("1", "False False False"), ("0", "True True True")):
        out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=root,
                             env={**os.environ, "PRTT_NO_NUMBA": value, "PYTHONPATH": root})
        assert out.stdout.strip() == want, out.stdout + out.stderr
    sc = corner_scene(GLOSSY_WALL, res=12)
    for value, want in (("1", "numpy"), ("0", "compiled")):
        monkeypatch.setenv("PRTT_NO_NUMBA", value)
        m = bake_scene(sc, str(tmp_path / value), BakeSettings(rays=16, bounces=1, bounce_rays=8), light=sky())
        assert {r["hit_shading"] for r in m["bounce"]["sets"]} == {want}


def test_a_numba_that_cannot_compile_the_loops_falls_back_to_numpy(tmp_path, monkeypatch):
    """numba imports but fails to compile (a numba or llvmlite this code was
    not written for): the bake shades with numpy, says so in the manifest and
    in core.base.jit.failures, and does not try again."""
    calls = []

    def refuse(*args):
        calls.append(args)
        raise RuntimeError("LLVM ERROR: intrinsic llvm.prefetch.p0i8 has a wrong type")

    monkeypatch.setattr(jit, "failures", {})
    monkeypatch.setattr(hit_kernel, "_probed", {})
    monkeypatch.setattr(hit_kernel, "_probe", refuse)
    sc = corner_scene(GLOSSY_WALL, res=12)
    for k in (1, 2):
        m = bake_scene(sc, str(tmp_path / str(k)), BakeSettings(rays=16, bounces=1, bounce_rays=8), light=sky())
        assert m["bounce"]["files"] and {r["hit_shading"] for r in m["bounce"]["sets"]} == {"numpy"}
    assert "prefetch" in jit.failures["prtt_addon.core.bake.estimators.hit_jit"]
    assert len(calls) == 1                                     # tried once per process


def test_column_store_equals_numpy_assignment():
    """hit_kernel.store_columns writes a chunk's rows into its texel columns
    as dst[:, cols] = src does, bit for bit: the compiled loops for a
    C-contiguous src and for the transposed texel-major rows the projections
    return, numpy for any other layout or dtype; columns it is not given
    keep their values."""
    assert hit_kernel.usable("columns", 0)
    rng = np.random.default_rng(3)
    base = rng.normal(size=(7, 300)).astype(np.float32)
    cols = np.sort(rng.choice(300, 40, replace=False)).astype(np.int64)
    rows = rng.normal(size=(40, 7)).astype(np.float32)
    srcs = {"contiguous": np.ascontiguousarray(rows.T), "transposed": rows.T, "float64": rows.T.astype(np.float64),
            "strided": np.asfortranarray(rng.normal(size=(7, 80)).astype(np.float32))[:, ::2]}
    for name, src in srcs.items():
        want, got = base.copy(), base.copy()
        want[:, cols] = src
        hit_kernel.store_columns(got, cols, src)
        assert np.array_equal(want, got), name
    mod = hit_kernel._jit()
    got = base.copy()
    mod.put_texel_rows(got, cols, rows)
    want = base.copy()
    want[:, cols] = rows.T
    assert np.array_equal(want, got)
    got = base.copy()
    mod.put_columns(got, cols, np.ascontiguousarray(rows.T))
    assert np.array_equal(want, got)
