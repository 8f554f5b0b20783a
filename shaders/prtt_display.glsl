/* Blender's colour management (view transform, look, display device) as a
 * table over a log2 shaper, then the display gamma: the GLSL twin of
 * prtt_addon/core/shading/display.py (DisplayTransform.encode), which says
 * the conventions. Needs the sampler displayLut (3D, linear filtering) and the
 * defines PRTT_SHAPER_LO and PRTT_SHAPER_HI (stops). */

/* Scene-linear radiance (times the exposure) -> display code values in [0, 1]. */
vec3 prtt_display(vec3 linear, float gamma_inv)
{
  float c = exp2(PRTT_SHAPER_LO);
  vec3 s = (log2(max(linear, vec3(0.0)) + c) - PRTT_SHAPER_LO) /
           (log2(exp2(PRTT_SHAPER_HI) + c) - PRTT_SHAPER_LO);
  s = clamp(s, 0.0, 1.0);
  float n = float(textureSize(displayLut, 0).x);
  vec3 d = textureLod(displayLut, (s * (n - 1.0) + 0.5) / n, 0.0).rgb;
  return pow(clamp(d, 0.0, 1.0), vec3(gamma_inv));
}

/* Display code values -> the linear value whose sRGB encoding they are: the
 * viewport's colour buffer encodes what a draw handler writes (IEC 61966-2-1). */
vec3 prtt_srgb_decode(vec3 c)
{
  return mix(c / 12.92, pow((c + 0.055) / 1.055, vec3(2.4)), step(vec3(0.04045), c));
}
