/* The per-point shading shared by the fragment modes (per pixel) and the vertex
 * baselines (per vertex): material, incident radiance by the selected product,
 * bounce textures, outgoing radiance. Needs `material` (struct PRTTMaterial),
 * `light`, and the samplers named below when their features are compiled in. */

/* The channel of roughTex that holds roughness: r for Blender's images; a
 * host whose roughness comes packed with other data (glTF's
 * metallicRoughness: G) defines it first. */
#ifndef PRTT_ROUGHNESS_CHANNEL
#define PRTT_ROUGHNESS_CHANNEL r
#endif

/* Material at a point with material-texture coordinates muv. */
void surface_material(vec2 muv, out vec3 albedo, out vec3 spec, out float exponent)
{
  int flags = int(material.params.w + 0.5);
  vec3 base = material.base.rgb;
  float roughness = material.params.x;
  if ((flags & 1) != 0) {
    base = bilinear_repeat(baseTex, muv).rgb;
  }
  if ((flags & 2) != 0) {
    roughness = bilinear_repeat(roughTex, muv).PRTT_ROUGHNESS_CHANNEL;
  }
  derive_material(base, material.base.a, roughness, material.params.y, albedo, spec, exponent);
}

#ifdef PRTT_BOUNCE
/* Bounce texture layout: layer c * SH_K4 + q holds channel c of coefficients 4q..4q+3.
 * Adds the bounce radiance B to Lp before the lobes (linear, so B is contracted alone). */
void add_bounce(vec2 uv, float w[SH_K], inout vec3 dc, inout vec3 glossy)
{
  for (int q = 0; q < SH_K4; q++) {
    vec4 r = textureLod(bounceTex, vec3(uv, float(q)), 0.0);
    vec4 g = textureLod(bounceTex, vec3(uv, float(SH_K4 + q)), 0.0);
    vec4 b = textureLod(bounceTex, vec3(uv, float(2 * SH_K4 + q)), 0.0);
    if (q == 0) {
      dc += vec3(r.x, g.x, b.x);
    }
    for (int c = 0; c < 4; c++) {
      int k = 4 * q + c;
      if (k < SH_K) {
        glossy += w[k] * vec3(r[c], g[c], b[c]);
      }
    }
  }
}
#endif

/* Outgoing radiance at a point with transfer T4, PRTT UV uv (for the bounce
 * textures), unit normal n and unit view vector v. */
vec3 shade_point(vec4 T4[SH_K4], vec2 uv, vec3 n, vec3 v, vec3 albedo, vec3 spec, float exponent)
{
#ifdef PRTT_DIFFUSE
  vec3 e = diffuse_dot(T4);
#  ifdef PRTT_BOUNCE
  vec3 dc = vec3(textureLod(bounceTex, vec3(uv, 0.0), 0.0).x,
                 textureLod(bounceTex, vec3(uv, float(SH_K4)), 0.0).x,
                 textureLod(bounceTex, vec3(uv, float(2 * SH_K4)), 0.0).x);
  e += PRTT_SQRT_4PI * dc;
#  endif
  return max(albedo / PRTT_PI * e, vec3(0.0));
#else
  float w[SH_K];
  if (any(greaterThan(spec, vec3(0.0)))) {
    glossy_weights(n, v, exponent, w);
  }
  else {
    for (int k = 0; k < SH_K; k++) {
      w[k] = 0.0;
    }
  }
  vec3 dc, glossy;
#  ifdef PRTT_TRIPLE_PRODUCT
  tp_contract(T4, w, dc, glossy);
#  else
  tpfl_contract(T4, w, dc, glossy);
#  endif
#  ifdef PRTT_BOUNCE
  add_bounce(uv, w, dc, glossy);
#  endif
  return outgoing(dc, glossy, albedo, spec);
#endif
}

#ifdef PRTT_SUN
/* The sun's direct light at a point (core.shading.shade.sun_direct): the
 * uniform block `sun` holds direction (xyz unit towards the sun, w = angle² / 16,
 * the disc's widening of a Phong lobe) and irradiance (rgb, W/m² facing it);
 * sunTex (r) the visible fraction of its disc, baked per texel at PRTT UV uv.
 * B = mask max(0, n.l) E (albedo / pi + spec (s' + 1) / (2 pi) max(0, r.l)^s'),
 * s' = 1 / (1 / s + w); the diffuse mode leaves the lobe out. */
vec3 sun_light(vec2 uv, vec3 n, vec3 v, vec3 albedo, vec3 spec, float exponent)
{
  vec3 l = sun.direction.xyz;
  float c = max(dot(n, l), 0.0) * textureLod(sunTex, uv, 0.0).r;
  if (!(c > 0.0)) {
    return vec3(0.0);
  }
  vec3 b = albedo / PRTT_PI;
#  ifndef PRTT_DIFFUSE
  if (any(greaterThan(spec, vec3(0.0)))) {
    vec3 r = 2.0 * dot(n, v) * n - v;
    float rl2 = dot(r, r);
    r = (rl2 > 0.0) ? r * inversesqrt(rl2) : n;
    float s = (exponent > 0.0) ? 1.0 / (1.0 / exponent + sun.direction.w) : 0.0;
    float rl = max(dot(r, l), 0.0);
    float lobe = (s > 0.0) ? pow(rl, s) : 1.0;
    b += spec * ((s + 1.0) / (2.0 * PRTT_PI) * lobe);
  }
#  endif
  return b * sun.irradiance.rgb * c;
}
#endif
