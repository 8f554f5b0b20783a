"""The GLSL library (shaders/prtt_common.glsl) function by function against
its numpy twins, on the GPU (Mesa llvmpipe in CI).

A harness shader includes the library unchanged and evaluates one function
per pixel of a 1-row float32 framebuffer, inputs read from float textures.
"""
import numpy as np
import pytest

from tests.blender_util import addon_bpy

pytestmark = pytest.mark.blender

HARNESS_MAIN = """
void main()
{
  int i = int(gl_FragCoord.x);
  vec4 a = texelFetch(inputA, ivec2(i, 0), 0);
  vec4 b = texelFetch(inputB, ivec2(i, 0), 0);
  vec4 c = texelFetch(inputC, ivec2(i, 0), 0);
  vec4 o = vec4(0.0);
#if TEST == 0
  float y[SH_K];
  sh_eval(a.xyz, y);
  for (int j = 0; j < 4; j++) { int k = 4 * Group + j; if (k < SH_K) { o[j] = y[k]; } }
#elif TEST == 1
  float A[SH_BANDS];
  phong_factors(a.x, A);
  for (int j = 0; j < 4; j++) { int l = 4 * Group + j; if (l < SH_BANDS) { o[j] = A[l]; } }
#elif TEST == 2
  o.x = phong_exponent(a.x);
#elif TEST == 3
  o.xyz = normal_mapped(a.xyz, b, c.xyz, c.w);
#elif TEST == 4
  float w[SH_K];
  glossy_weights(a.xyz, b.xyz, b.w, w);
  for (int j = 0; j < 4; j++) { int k = 4 * Group + j; if (k < SH_K) { o[j] = w[k]; } }
#elif TEST == 5
  vec3 albedo, spec;
  float s;
  derive_material(a.xyz, a.w, b.x, b.y, albedo, spec, s);
  o = (Group == 0) ? vec4(albedo, s) : vec4(spec, 0.0);
#endif
  FragColor = o;
}
"""


def run_harness(test: int, bands: int, inputs, groups: int = 1) -> np.ndarray:
    """Evaluate harness TEST for N inputs (each (N, 4)); returns (groups, N, 4)."""
    addon_bpy()                       # bpy first: it provides the gpu module
    import gpu
    from gpu_extras.batch import batch_for_shader

    from prtt_addon.blender.preview.offscreen import ensure_gpu
    from prtt_addon.core.preview.shader_source import read_source
    ensure_gpu()
    n = inputs[0].shape[0]
    info = gpu.types.GPUShaderCreateInfo()
    k = bands * bands
    for name, value in (("SH_BANDS", bands), ("SH_K", k), ("SH_K4", (k + 3) // 4), ("TEST", test)):
        info.define(name, str(value))
    info.vertex_in(0, "VEC2", "pos")
    for slot, name in enumerate(("inputA", "inputB", "inputC")):
        info.sampler(slot, "FLOAT_2D", name)
    info.push_constant("INT", "Group")
    info.fragment_out(0, "VEC4", "FragColor")
    info.vertex_source("void main() { gl_Position = vec4(pos, 0.0, 1.0); }")
    info.fragment_source(read_source("prtt_common.glsl") + HARNESS_MAIN)
    sh = gpu.shader.create_from_info(info)
    texs = []
    for a in list(inputs) + [np.zeros((n, 4))] * (3 - len(inputs)):
        a = np.ascontiguousarray(a, np.float32)
        texs.append(gpu.types.GPUTexture((n, 1), format="RGBA32F", data=gpu.types.Buffer("FLOAT", a.size, a.ravel())))
    batch = batch_for_shader(sh, "TRI_FAN", {"pos": ((-1, -1), (1, -1), (1, 1), (-1, 1))})
    out = np.zeros((groups, n, 4), np.float32)
    off = gpu.types.GPUOffScreen(n, 1, format="RGBA32F")
    try:
        with off.bind():
            fb = gpu.state.active_framebuffer_get()
            for g in range(groups):
                fb.clear(color=(0, 0, 0, 0))
                sh.bind()
                for name, t in zip(("inputA", "inputB", "inputC"), texs):
                    sh.uniform_sampler(name, t)
                if groups > 1:
                    sh.uniform_int("Group", g)
                batch.draw(sh)
                buf = gpu.types.Buffer("FLOAT", n * 4)
                fb.read_color(0, 0, n, 1, 4, 0, "FLOAT", data=buf)
                out[g] = np.asarray(buf).reshape(n, 4)
    finally:
        off.free()
    return out


def unit_dirs(n, seed=0):
    d = np.random.default_rng(seed).normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    poles = np.array([[0, 0, 1.0], [0, 0, -1.0], [1.0, 0, 0], [0, 1.0, 0]])
    return np.concatenate([poles, d]).astype(np.float32)


@pytest.mark.parametrize("bands", [1, 2, 5, 8])
def test_sh_eval_matches_basis(bands):
    from prtt_addon.core.sh.basis import eval_basis, float32_error_bound
    d = unit_dirs(200)
    K = bands * bands
    got = run_harness(0, bands, [np.c_[d, np.zeros(len(d))]], groups=(K + 3) // 4)
    got = got.transpose(1, 0, 2).reshape(len(d), -1)[:, :K]
    want = eval_basis(d.astype(np.float64), bands, normalize=True)
    assert np.abs(got - want).max() <= float32_error_bound(bands)


def test_phong_factors_and_exponent():
    from prtt_addon.core.sh.zonal import phong_factors
    from prtt_addon.core.shading.materials import phong_exponent
    s = np.array([0.0, 0.5, 1.0, 7.5, 61.0, 499.5, 5000.0, 10000.0])
    got = run_harness(1, 8, [np.c_[s, np.zeros((len(s), 3))]], groups=2)
    got = got.transpose(1, 0, 2).reshape(len(s), -1)[:, :8]
    np.testing.assert_allclose(got, phong_factors(s, 8), rtol=2e-6, atol=1e-7)
    r = np.array([0.0, 1e-7, 0.01, 0.1, 0.3, 0.5, 0.8, 1.0, 1.5, -0.2])
    got = run_harness(2, 1, [np.c_[r, np.zeros((len(r), 3))]])[0, :, 0]
    np.testing.assert_allclose(got, phong_exponent(r.astype(np.float32)), rtol=2e-6, atol=1e-6)


def test_normal_mapping_matches_gbuffer():
    from prtt_addon.core.texels.gbuffer import perturb_normals
    rng = np.random.default_rng(3)
    n = unit_dirs(64, 1).astype(np.float64)
    tan = rng.normal(size=(len(n), 3))
    tan[:3] = n[:3]                                      # tangent parallel to the normal: kept normal
    sign = np.where(rng.random(len(n)) < 0.5, -1.0, 1.0)
    rgb = rng.random((len(n), 3))
    rgb[3] = 0.5                                          # mapped vector (0, 0, 0): kept normal
    for strength in (1.0, 0.6, 2.0):
        want, _ = perturb_normals(n, tan, sign, rgb, strength)
        got = run_harness(3, 1, [np.c_[n, np.zeros(len(n))], np.c_[tan, sign], np.c_[rgb, np.full(len(n), strength)]])
        np.testing.assert_allclose(got[0, :, :3], want, atol=3e-6)


def test_glossy_weights_and_material():
    from prtt_addon.core.sh.basis import eval_basis
    from prtt_addon.core.shading.materials import derive
    from prtt_addon.core.shading.shade import lobe_factors, reflect
    n = unit_dirs(50, 2).astype(np.float64)
    v = unit_dirs(50, 5).astype(np.float64)
    s = np.linspace(0.0, 2000.0, len(n))
    got = run_harness(4, 5, [np.c_[n, np.zeros(len(n))], np.c_[v, s]], groups=7)
    got = got.transpose(1, 0, 2).reshape(len(n), -1)[:, :25]
    r = reflect(v, n)
    r /= np.linalg.norm(r, axis=1, keepdims=True)
    want = lobe_factors(s, 5) * eval_basis(r, 5)
    assert np.abs(got - want).max() <= 2e-6
    rng = np.random.default_rng(4)
    base, metal, rough, f0 = rng.random((40, 3)), rng.random(40), rng.random(40), 0.08 * rng.random(40)
    got = run_harness(5, 1, [np.c_[base, metal], np.c_[rough, f0, np.zeros((40, 2))]], groups=2)
    # derive() takes (ior, specular); specular = f0 / 0.08 at ior 1.5 gives the same F0 (0.04 at 0.5).
    want = derive(base, metal, rough, f0 / 0.08, np.full(40, 1.5))
    np.testing.assert_allclose(got[0, :, :3], want.albedo, atol=1e-6)
    np.testing.assert_allclose(got[1, :, :3], want.spec, atol=1e-6)
    # s = 0.5 / r^4 - 0.5 cancels near r = 1: compare with the float32 inputs, absolute floor.
    want_s = derive(base, metal, rough.astype(np.float32), f0 / 0.08, np.full(40, 1.5)).exponent
    np.testing.assert_allclose(got[0, :, 3], want_s, rtol=2e-6, atol=1e-6)
