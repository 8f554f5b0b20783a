"""The Principled BSDF's layering (core.shading.layering): its tables against
their own quadrature, the shader file against the tables, and the weights
against Cycles' Diffuse and Glossy Color passes (what Cycles' Principled BSDF
takes from the diffuse at each view angle)."""
import re

import numpy as np
import pytest

from prtt_addon.core.shading import layering as L
from prtt_addon.core.shading.materials import phong_exponent


def _glsl_arrays(text):
    out = {}
    for name, body in re.findall(r"const float (\w+)\[\d+\] = float\[\d+\]\(([^;]*)\);", text):
        out[name] = np.array([float(x) for x in body.replace("\n", " ").split(",")], np.float64)
    return out


def test_shader_file_holds_the_tables():
    """shaders/prtt_layering.glsl is the tables' float32 values (regenerate:
    python -m prtt_addon.dev.layering_table), in the order the GLSL reads."""
    from prtt_addon.core.preview.shader_source import read_source
    got = _glsl_arrays(read_source("prtt_layering.glsl"))
    t = L.tables()
    for name, key in (("PRTT_LAYER_E", "E"), ("PRTT_LAYER_S5", "s5"), ("PRTT_LAYER_S", "s"),
                      ("PRTT_LAYER_EAVG", "E_avg"), ("PRTT_LAYER_BAVG", "blend_avg")):
        np.testing.assert_allclose(got[name], t[key].ravel(), rtol=1e-6, atol=1e-7, err_msg=name)


def _direct(mu, r, f0):
    """a_d at one point by quadrature, no table: E, s and the averages at
    this (mu, r, z) exactly (E_avg by its own mu quadrature)."""
    z = f0 ** 0.25
    w, vh = L._lobe(mu, r)
    E = w.sum()
    s = (w * L.blend(vh, z)).sum() / E
    mus = (np.arange(64) + 0.5) / 64
    E_avg = 2.0 * np.mean([L._lobe(m, r)[0].sum() * m for m in mus])
    fss = f0 + (1.0 - f0) * L._average(lambda c: L.blend(c, z))
    return L.darkening(E, E_avg, fss) * (f0 + (1.0 - f0) * s)


@pytest.mark.parametrize("mu,r,f0", [(0.23, 0.37, 0.04), (0.71, 0.55, 0.04), (0.5, 0.83, 0.08),
                                     (0.9, 0.2, 0.02), (0.33, 0.65, 0.034)])
def test_table_lookup_against_direct_quadrature(mu, r, f0):
    """Between the nodes, the interpolated dielectric albedo is within 0.004
    of the quadrature at that point (1 - a_d, the diffuse weight, within 0.5 %)."""
    dw, gw = L.layer_weights([mu], phong_exponent([r]), [f0], [0.0], [[f0] * 3], tab=L.float32_tables())
    a = _direct(mu, r, f0)
    assert abs((1.0 - dw[0]) - a) < 0.004, (1.0 - dw[0], a)
    np.testing.assert_allclose(gw[0], a, atol=0.004)


@pytest.mark.parametrize("rough,mu", [(0.3, 0.8), (0.7, 0.8), (1.0, 0.5), (0.7, 0.3)])
def test_multiscatter_sun_lobe_keeps_a_white_metals_energy(rough, mu):
    """A white metal (F = 1): the sun's lobe (shade.sun_glossy, Multiscatter
    GGX) integrated over every direction of the light gives the view all of
    it back, 1 within 0.5 % (the tables' interpolation); single scattering
    keeps 0.45-0.99 of it here."""
    from prtt_addon.core.shading.materials import derive
    from prtt_addon.core.shading.shade import sun_glossy
    x, wx = np.polynomial.legendre.leggauss(200)
    ct, phi = 0.5 * (x + 1.0), np.pi * (x + 1.0)
    T, P = np.meshgrid(ct, phi, indexing="ij")
    W = np.outer(wx * 0.5, wx * np.pi).ravel()
    st = np.sqrt(1.0 - T ** 2)
    ls = np.stack([st * np.cos(P), st * np.sin(P), T], -1).reshape(-1, 3)
    k = ls.shape[0]
    n = np.tile([0.0, 0.0, 1.0], (k, 1))
    v = np.tile([np.sqrt(1.0 - mu * mu), 0.0, mu], (k, 1))
    p = derive(np.ones((k, 3)), np.ones(k), np.full(k, rough), np.full(k, 0.5), np.full(k, 1.5))
    got = {}
    for multi in (True, False):
        f = sun_glossy(n, v, ls, p, 0.0, multi=multi)[:, 0]
        got[multi] = float(np.sum(W * f * ls[:, 2]))
    assert abs(got[True] - 1.0) < 0.005, got
    assert got[False] < got[True] - 0.01 or rough < 0.5, got


def test_weights_without_a_specular_layer_are_lambert():
    """F0 0 and no metal (a Diffuse BSDF): diffuse weight exactly 1, glossy 0."""
    dw, gw = L.layer_weights(np.linspace(0, 1, 7), np.full(7, 7.5), np.zeros(7), np.zeros(7), np.zeros((7, 3)))
    assert np.all(dw == 1.0) and np.all(gw == 0.0)


def _cycles_sphere(bpy, path, rough, ior=1.5, metallic=0.0, base=(1.0, 1.0, 1.0), res=96):
    """Cycles' Diffuse and Glossy Color passes of a Principled sphere seen
    orthographically from +Z: (mu (res, res), diffuse colour, glossy colour (res, res, 3), inside)."""
    import OpenEXR
    bpy.ops.wm.read_factory_settings(use_empty=True)
    sc = bpy.context.scene
    bpy.ops.mesh.primitive_uv_sphere_add(segments=192, ring_count=96, radius=1.0)
    ob = bpy.context.object
    bpy.ops.object.shade_smooth()
    m = bpy.data.materials.new("m")
    m.use_nodes = True
    p = m.node_tree.nodes["Principled BSDF"]
    p.inputs["Base Color"].default_value = (*base, 1.0)
    p.inputs["Roughness"].default_value = rough
    p.inputs["IOR"].default_value = ior
    p.inputs["Metallic"].default_value = metallic
    ob.data.materials.append(m)
    cam = bpy.data.cameras.new("c")
    cam.type, cam.ortho_scale = "ORTHO", 2.0
    co = bpy.data.objects.new("c", cam)
    sc.collection.objects.link(co)
    co.location, sc.camera = (0.0, 0.0, 10.0), co
    sc.render.engine = "CYCLES"
    sc.cycles.samples, sc.cycles.device = 2, "CPU"
    sc.render.resolution_x = sc.render.resolution_y = res
    sc.render.resolution_percentage = 100
    sc.cycles.pixel_filter_type, sc.cycles.filter_width = "BOX", 0.01
    layer = sc.view_layers[0]
    layer.use_pass_diffuse_color = layer.use_pass_glossy_color = True
    sc.world = bpy.data.worlds.new("w")
    fmt = sc.render.image_settings
    if hasattr(fmt, "media_type"):
        fmt.media_type = "MULTI_LAYER_IMAGE"
    else:
        fmt.file_format = "OPEN_EXR_MULTILAYER"
    sc.render.filepath = path
    bpy.ops.render.render(write_still=True)
    with OpenEXR.File(path) as f:
        ch = {k: v for part in f.parts for k, v in part.channels.items()}

    def plane(*names):
        key = next(k for k in ch if any(k.endswith(f".{n}") or f".{n}." in k for n in names))
        px = np.array(ch[key].pixels, np.float64)
        return (px[..., :3] if px.ndim == 3 else px)[::-1]
    c = (np.arange(res) + 0.5) / res * 2.0 - 1.0
    X, Y = np.meshgrid(c, c)
    rr = X * X + Y * Y
    return np.sqrt(np.maximum(0.0, 1.0 - rr)), plane("Diffuse Color", "DiffCol"), plane("Glossy Color", "GlossCol"), rr < 0.97


@pytest.mark.blender
def test_weights_match_cycles_colour_passes(tmp_path):
    """Over a Principled sphere (Multiscatter GGX, Blender's default), Cycles'
    Diffuse Color is base (1 - m) x the diffuse weight and its Glossy Color
    the specular layers' albedo: in bands of n.v from 0.17 to 1, the mean of
    PRTT's weights at each pixel's n.v within 1 % (diffuse) and 0.01
    (glossy; 0.0085 at n.v 0.2 and roughness 0.5, 6 % of the layer's
    albedo there) of Cycles', for a dielectric at two roughnesses, a coloured
    metal and a half-metal; the unlayered model (weight 1) is 4-30 % off at
    the same bands, so the test can fail. (Single pixels near the rim are
    further apart: n.v changes across a pixel there.)"""
    pytest.importorskip("bpy")
    from tests.blender_util import fresh_bpy
    bpy = fresh_bpy()
    cases = ((0.5, 1.5, 0.0, (1.0, 1.0, 1.0)), (0.25, 1.45, 0.0, (1.0, 1.0, 1.0)),
             (0.4, 1.5, 1.0, (0.9, 0.6, 0.3)), (0.8, 1.5, 0.5, (0.5, 0.7, 0.9)))
    for rough, ior, metal, base in cases:
        mu, dc, gc, ok = _cycles_sphere(bpy, str(tmp_path / "s.exr"), rough, ior, metal, base)
        mu, dc, gc = mu[ok], dc[ok], gc[ok]
        f0 = ((ior - 1.0) / (ior + 1.0)) ** 2
        C = np.array(base)
        spec = np.tile((1.0 - metal) * f0 + metal * C, (mu.size, 1))
        dw, gw = L.layer_weights(mu, phong_exponent(np.full(mu.size, rough)), np.full(mu.size, f0),
                                 np.full(mu.size, metal), spec)
        worst_unlayered = 0.0
        for lo, hi in ((0.17, 0.25), (0.25, 0.4), (0.4, 0.6), (0.6, 0.8), (0.8, 1.0)):
            b = (mu >= lo) & (mu < hi)
            assert b.sum() > 50
            if metal < 1.0:
                cyc = (dc[b] / (C * (1.0 - metal))).mean(axis=0)          # Cycles' diffuse weight
                assert np.abs(dw[b].mean() / cyc - 1.0).max() < 0.01, (rough, metal, lo, dw[b].mean(), cyc)
                worst_unlayered = max(worst_unlayered, float(np.abs(1.0 / cyc - 1.0).max()))
            else:
                assert np.abs(dc[b]).max() == 0.0
            assert np.abs(gw[b].mean(axis=0) - gc[b].mean(axis=0)).max() < 0.01, (rough, metal, lo)
        if metal < 1.0:
            assert worst_unlayered > 0.04, worst_unlayered
