/* PRTT shader library: pure functions (no resources).
 *
 * Conventions (docs/sh-conventions.md, docs/shading.md):
 *   - real orthonormal SH, index k = l*l + l + m, Z-up world, Condon-Shortley phase;
 *   - transfer T travels as vec4 T4[SH_K4]: coefficient k is T4[k / 4][k % 4];
 *   - `view` v is the unit vector from the surface towards the eye, r = 2 (n.v) n - v.
 * Every formula here has a numpy twin it is tested against (tests/test_shader_harness.py):
 *   sh_eval          <-> prtt_addon.core.sh.basis.basis_unchecked (same recurrence)
 *   phong_factors    <-> prtt_addon.core.sh.zonal.phong_factors
 *   phong_exponent   <-> prtt_addon.core.shading.materials.phong_exponent
 *   glossy_weights,
 *   outgoing         <-> prtt_addon.core.shading.shade.outgoing
 * Requires the defines SH_BANDS, SH_K (= SH_BANDS^2) and SH_K4 (= ceil(SH_K / 4)).
 */

#define PRTT_PI 3.14159265358979
#define PRTT_SQRT2 1.41421356237310
#define PRTT_SQRT_4PI 3.54490770181103
#define PRTT_MAX_EXPONENT 10000.0

float sh_coef(vec4 T4[SH_K4], int k)
{
  return T4[k >> 2][k & 3];
}

/* All SH_K basis functions at the unit direction d, by the normalised
 * three-term recurrence on Pbar_l^m = K_lm P_l^m / sin^m and
 * (cm, sm) = Re/Im (x + i y)^m: no trigonometry, exact at the poles. */
void sh_eval(vec3 d, out float y[SH_K])
{
  float cm = 1.0;
  float sm = 0.0;
  float sect = 0.28209479177387814; /* sqrt(1 / (4 pi)) = Pbar_0^0 */
  for (int m = 0; m < SH_BANDS; m++) {
    if (m > 0) {
      float c2 = d.x * cm - d.y * sm;
      sm = d.x * sm + d.y * cm;
      cm = c2;
      sect *= -sqrt(float(2 * m + 1) / (2.0 * float(m)));
    }
    float p_prev = sect;
    float p_cur = 0.0;
    for (int l = m; l < SH_BANDS; l++) {
      float p;
      if (l == m) {
        p = p_prev;
      }
      else if (l == m + 1) {
        p_cur = sqrt(float(2 * m + 3)) * d.z * p_prev;
        p = p_cur;
      }
      else {
        float fl = float(l);
        float fm = float(m);
        float a = sqrt((4.0 * fl * fl - 1.0) / (fl * fl - fm * fm));
        float b = sqrt(((fl - 1.0) * (fl - 1.0) - fm * fm) / (4.0 * (fl - 1.0) * (fl - 1.0) - 1.0));
        p = a * (d.z * p_cur - b * p_prev);
        p_prev = p_cur;
        p_cur = p;
      }
      int k0 = l * l + l;
      if (m == 0) {
        y[k0] = p;
      }
      else {
        y[k0 + m] = PRTT_SQRT2 * p * cm;
        y[k0 - m] = PRTT_SQRT2 * p * sm;
      }
    }
  }
}

/* Funk-Hecke factors A_l of the normalised Phong lobe (s + 1) / (2 pi) cos^s:
 * A_0 = 1, A_1 = (s + 1) / (s + 2), A_l = A_{l-2} (s - l + 2) / (s + l + 1). */
void phong_factors(float s, out float A[SH_BANDS])
{
  A[0] = 1.0;
  for (int l = 1; l < SH_BANDS; l++) {   /* (a loop, so SH_BANDS = 1 never indexes A[1]) */
    if (l == 1) {
      A[l] = (s + 1.0) / (s + 2.0);
    }
    else {
      A[l] = A[l - 2] * (s - float(l) + 2.0) / (s + float(l) + 1.0);
    }
  }
}

/* Principled roughness -> Phong exponent about the reflection vector:
 * s = 1 / (2 alpha^2) - 1/2, alpha = roughness^2, clamped to [0, 10000]. */
float phong_exponent(float roughness)
{
  float r = clamp(roughness, 0.0, 1.0);
  float a2 = r * r * r * r;
  if (!(a2 > 0.0)) {
    return PRTT_MAX_EXPONENT;
  }
  return clamp(0.5 / a2 - 0.5, 0.0, PRTT_MAX_EXPONENT);
}

/* Bilinear lookup with repeat wrapping, texel centres at (i + 0.5) / W, done by
 * hand so that it is exact and the same on every GPU (core.texels.gbuffer.sample_bilinear). */
vec4 bilinear_repeat(sampler2D tex, vec2 uv)
{
  ivec2 size = textureSize(tex, 0);
  vec2 x = uv * vec2(size) - 0.5;
  vec2 x0 = floor(x);
  vec2 f = x - x0;
  ivec2 i0 = ivec2(x0);
  ivec2 a = ((i0 % size) + size) % size;
  ivec2 b = (((i0 + 1) % size) + size) % size;
  vec4 t00 = texelFetch(tex, ivec2(a.x, a.y), 0);
  vec4 t10 = texelFetch(tex, ivec2(b.x, a.y), 0);
  vec4 t01 = texelFetch(tex, ivec2(a.x, b.y), 0);
  vec4 t11 = texelFetch(tex, ivec2(b.x, b.y), 0);
  return mix(mix(t00, t10, f.x), mix(t01, t11, f.x), f.y);
}

/* Unit normal from an interpolated one; falls back to `fallback` (already unit)
 * where the interpolation passes through zero (corner normals that cancel). */
vec3 safe_normal(vec3 n, vec3 fallback)
{
  float len2 = dot(n, n);
  return (len2 > 1e-12) ? n * inversesqrt(len2) : fallback;
}

/* Tangent-space normal map (core.texels.gbuffer.apply_normal_maps): encoded 0..1 rgb,
 * Gram-Schmidt tangent, bitangent sign, blend by strength. */
vec3 normal_mapped(vec3 n, vec4 tangent, vec3 encoded, float strength)
{
  vec3 ts = 2.0 * encoded - 1.0;
  vec3 t = tangent.xyz - n * dot(tangent.xyz, n);
  float tl2 = dot(t, t);
  if (!(tl2 > 1e-24)) {
    return n;
  }
  t *= inversesqrt(tl2);
  vec3 b = ((tangent.w < 0.0) ? -1.0 : 1.0) * cross(n, t);
  vec3 m = ts.x * t + ts.y * b + ts.z * n;
  float ml2 = dot(m, m);
  if (!(ml2 > 1e-24)) {
    return n;
  }
  m *= inversesqrt(ml2);
  vec3 blended = n + (m - n) * max(strength, 0.0);
  float bl2 = dot(blended, blended);
  return (bl2 > 0.0) ? blended * inversesqrt(bl2) : n;
}

/* Lambert albedo, specular weight and Phong exponent from Principled values
 * (core.shading.materials.derive). */
void derive_material(vec3 base, float metallic, float roughness, float f0,
                     out vec3 albedo, out vec3 spec, out float exponent)
{
  base = max(base, vec3(0.0));
  metallic = clamp(metallic, 0.0, 1.0);
  albedo = base * (1.0 - metallic);
  spec = (1.0 - metallic) * vec3(f0) + metallic * base;
  exponent = phong_exponent(roughness);
}

/* Glossy weights w_k = A_l(s) y_k(r) at the reflection direction r = 2 (n.v) n - v:
 * the normalised Phong lobe's Funk-Hecke factors times the basis, so that the
 * glossy radiance is sum_k w_k Lp_k (core.shading.shade.outgoing). */
void glossy_weights(vec3 n, vec3 v, float exponent, out float w[SH_K])
{
  vec3 r = 2.0 * dot(n, v) * n - v;
  float rl2 = dot(r, r);
  r = (rl2 > 0.0) ? r * inversesqrt(rl2) : n;
  sh_eval(r, w);
  float A[SH_BANDS];
  phong_factors(exponent, A);
  for (int l = 0; l < SH_BANDS; l++) {
    for (int k = l * l; k < (l + 1) * (l + 1); k++) {
      w[k] *= A[l];
    }
  }
}

/* Outgoing radiance from the incident radiance's DC term Lp_0 and its glossy
 * contraction sum_k w_k Lp_k (core.shading.shade.outgoing):
 * B = albedo / pi * sqrt(4 pi) Lp_0 + spec * glossy, clamped at 0 (SH ringing). */
vec3 outgoing(vec3 dc, vec3 glossy, vec3 albedo, vec3 spec)
{
  return max(albedo * (PRTT_SQRT_4PI / PRTT_PI) * dc + spec * glossy, vec3(0.0));
}
