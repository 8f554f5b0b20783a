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
  /* The Principled layering (prtt_layering.glsl): the specular layer's
   * albedo at this view angle is taken from the diffuse beneath and weighs
   * the glossy lobe (core.shading.shade.outgoing). */
  float dw;
  vec3 gw;
  prtt_layer_weights(dot(n, v), exponent, material.params.y, material.base.w, spec, dw, gw);
  albedo *= dw;
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
  return outgoing(dc, glossy, albedo, gw);
#endif
}

#if defined(PRTT_SUN) || defined(PRTT_LAMPS)
/* Unpolarised Fresnel reflectance of a dielectric of relative IOR eta at
 * cos(incidence) c (core.shading.shade.fresnel_dielectric). */
float prtt_fresnel_dielectric(float c, float eta)
{
  float g2 = eta * eta - 1.0 + c * c;
  if (!(g2 > 0.0)) {
    return 1.0;
  }
  float g = sqrt(g2);
  float a = (g - c) / (g + c);
  float b = (c * (g + c) - 1.0) / (c * (g - c) + 1.0);
  return 0.5 * a * a * (1.0 + b * b);
}

float prtt_smith_lambda(float c, float a2)
{
  float c2 = clamp(c * c, 1e-12, 1.0);
  return 0.5 * (sqrt(1.0 + a2 * (1.0 - c2) / c2) - 1.0);
}

/* A small light's specular BRDF (core.shading.shade.sun_glossy): GGX of
 * alpha'^2 = alpha^2 + angle^2 / 32 (alpha^2 = 1 / (2 s + 1), widened by the
 * light's disc of full angle `angle`: w = angle^2 / 16), Smith's
 * height-correlated masking, the dielectric Fresnel of the material's F0
 * plus Schlick's for its metallic part, each with Multiscatter GGX's factor
 * (prtt_layer_multiscatter): D G F / (4 n.v n.l). */
vec3 prtt_glossy(vec3 n, vec3 v, vec3 l, vec3 spec, float exponent, float w)
{
  float nv = dot(n, v);
  float nl = dot(n, l);
  vec3 h = v + l;
  float hh = dot(h, h);
  if (!(nv > 0.0) || !(nl > 0.0) || !(hh > 0.0)) {
    return vec3(0.0);
  }
  h *= inversesqrt(hh);
  float nh = clamp(dot(n, h), 0.0, 1.0);
  float vh = clamp(dot(v, h), 0.0, 1.0);
  float a2 = 1.0 / (2.0 * max(exponent, 0.0) + 1.0);
  float a2s = a2 + 0.5 * w;
  float t = nh * nh * (a2s - 1.0) + 1.0;
  float D = a2s / (PRTT_PI * t * t);
  float G = 1.0 / (1.0 + prtt_smith_lambda(nv, a2) + prtt_smith_lambda(nl, a2));
  float m = material.base.w;
  float f0 = material.params.y;
  float sf = sqrt(clamp(f0, 0.0, 0.999));
  vec3 metal = spec - vec3((1.0 - m) * f0);      /* metallic x base colour */
  float q = pow(1.0 - vh, 5.0);
  /* Multiscatter GGX (Blender's default): each part times its factor at n.v. */
  float ms_d;
  vec3 ms_m;
  prtt_layer_multiscatter(nv, exponent, f0, m, spec, ms_d, ms_m);
  vec3 F = vec3((1.0 - m) * prtt_fresnel_dielectric(vh, (1.0 + sf) / (1.0 - sf)) * ms_d)
           + (metal + (vec3(m) - metal) * q) * ms_m;
  return F * (D * G / (4.0 * nv * nl));
}

#endif

#ifdef PRTT_LAMPS
/* Point and spot lamps' direct light at world point p (core.shading.shade.
 * lamp_direct): the uniform block `lamps` holds, per lamp i < info.x,
 * position[i] (xyz world, w the sphere's radius), intensity[i] (rgb W/sr,
 * w the spot's smoothstep scale 1 / ((1 - cos half cone) blend)) and
 * spot[i] (xyz the unit axis it shines along, w cos half its cone; -2 for
 * a point lamp); lampTex channel i the visible fraction of lamp i's sphere,
 * baked per texel at PRTT UV uv.
 * B = sum_i mask_i spot_i max(0, n.l_i) I_i / r_i^2 (dw albedo / pi + glossy),
 * the glossy lobe widened by the sphere's disc (full angle 2 asin(R / r)). */
vec3 lamp_light(vec2 uv, vec3 p, vec3 n, vec3 v, vec3 albedo, vec3 spec, float exponent)
{
  vec4 m = textureLod(lampTex, uv, 0.0);
  int count = int(lamps.info.x + 0.5);
  float dw;
  vec3 gw;
  prtt_layer_weights(dot(n, v), exponent, material.params.y, material.base.w, spec, dw, gw);
  vec3 sum = vec3(0.0);
  for (int i = 0; i < 4; i++) {
    if (i >= count) {
      break;
    }
    vec3 to = lamps.position[i].xyz - p;
    float r2 = max(dot(to, to), 1e-12);
    vec3 l = to * inversesqrt(r2);
    /* The cone averaged over the sphere's disc (angular radius a): five
     * Gauss-Chebyshev nodes over the angle from the axis (Lamp.spot). */
    float a = asin(min(lamps.position[i].w * inversesqrt(r2), 1.0));
    float th = acos(clamp(dot(-l, lamps.spot[i].xyz), -1.0, 1.0));
    vec4 cs = cos(vec4(th - 0.8660254 * a, th - 0.5 * a, th + 0.5 * a, th + 0.8660254 * a));
    vec4 t = clamp((cs - vec4(lamps.spot[i].w)) * lamps.intensity[i].w, 0.0, 1.0);
    float t0 = clamp((cos(th) - lamps.spot[i].w) * lamps.intensity[i].w, 0.0, 1.0);
    float sm = dot(t * t * (3.0 - 2.0 * t), vec4(1.0, 3.0, 3.0, 1.0) / 12.0) + t0 * t0 * (3.0 - 2.0 * t0) / 3.0;
    float c = max(dot(n, l), 0.0) * m[i] * sm;
    if (!(c > 0.0)) {
      continue;
    }
    vec3 b = albedo * dw / PRTT_PI;
#  ifndef PRTT_DIFFUSE
    if (any(greaterThan(spec, vec3(0.0)))) {
      b += prtt_glossy(n, v, l, spec, exponent, a * a / 4.0);      /* (2a)^2 / 16 */
    }
#  endif
    sum += b * lamps.intensity[i].rgb * (c / r2);
  }
  return sum;
}
#endif

#ifdef PRTT_SUN
/* The sun's specular BRDF: prtt_glossy widened by its disc (sun.direction.w = angle^2 / 16). */
vec3 sun_glossy(vec3 n, vec3 v, vec3 l, vec3 spec, float exponent)
{
  return prtt_glossy(n, v, l, spec, exponent, sun.direction.w);
}

/* The visible fraction of the sun's disc at PRTT UV uv: sunTex r is the
 * baked mask; where the bake stored sub-texel edges (core.bake.estimators.
 * sun_edge) g is the signed distance to the shadow edge's line and a the
 * penumbra's half-width (texels), b = 1 where the line holds. Filtered
 * bilinearly, d is exact on a plane; b below 1 means a texel around uv left
 * it to the mask. A mask without edges (one channel) reads b = 0. */
float sun_visible(vec2 uv)
{
  vec4 m = textureLod(sunTex, uv, 0.0);
  if (m.b > 0.999 && m.a > 0.0) {
    /* A uniform disc behind a straight edge s radii from its centre (sun_edge.profile). */
    float s = clamp(m.g / m.a, -1.0, 1.0);
    return 1.0 - (acos(s) - s * sqrt(1.0 - s * s)) / PRTT_PI;
  }
  return m.r;
}

/* The sun's direct light at a point (core.shading.shade.sun_direct): the
 * uniform block `sun` holds direction (xyz unit towards the sun, w = angle² / 16)
 * and irradiance (rgb, W/m² facing it); sun_visible the visible fraction of
 * its disc, baked per texel at PRTT UV uv.
 * B = mask max(0, n.l) E (dw albedo / pi + sun_glossy), dw the layering's
 * diffuse weight (prtt_layering.glsl); the diffuse mode leaves the lobe out. */
vec3 sun_light(vec2 uv, vec3 n, vec3 v, vec3 albedo, vec3 spec, float exponent)
{
  vec3 l = sun.direction.xyz;
  float c = max(dot(n, l), 0.0) * sun_visible(uv);
  if (!(c > 0.0)) {
    return vec3(0.0);
  }
  float dw;
  vec3 gw;
  prtt_layer_weights(dot(n, v), exponent, material.params.y, material.base.w, spec, dw, gw);
  vec3 b = albedo * dw / PRTT_PI;
#  ifndef PRTT_DIFFUSE
  if (any(greaterThan(spec, vec3(0.0)))) {
    b += sun_glossy(n, v, l, spec, exponent);
  }
#  endif
  return b * sun.irradiance.rgb * c;
}
#endif
