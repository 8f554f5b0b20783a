/* Per-fragment PRT with transfer textures: the paper's method (TPFL), the full
 * triple product (TP) and the diffuse fast path, chosen by defines. */
void main()
{
  vec3 v = view_vector(wpos);
  /* Derivatives before any branch: the geometric normal, facing the viewer, is
   * the fallback where interpolated corner normals cancel out. */
  vec3 face = cross(dFdx(wpos), dFdy(wpos));
  face = (dot(face, face) > 0.0) ? normalize(face) : v;
  face = (dot(face, v) < 0.0) ? -face : face;
  vec3 n = safe_normal(wnor, face);

  vec3 albedo, spec;
  float exponent;
  surface_material(mat_uv, albedo, spec, exponent);
  if ((int(material.params.w + 0.5) & 4) != 0) {
    n = normal_mapped(n, wtan, bilinear_repeat(normalTex, nm_uv).rgb, material.params.z);
  }

  vec4 T4[SH_K4];
  for (int q = 0; q < SH_K4; q++) {
    T4[q] = textureLod(transferTex, vec3(prtt_uv, float(q)), 0.0);
  }
  vec3 color = shade_point(T4, prtt_uv, n, v, albedo, spec, exponent);
#ifdef PRTT_SUN
  color += sun_light(prtt_uv, n, v, albedo, spec, exponent);
#endif
#ifdef PRTT_LAMPS
  color += lamp_light(prtt_uv, wpos, n, v, albedo, spec, exponent);
#endif
  FragColor = vec4(color * view.params.x, 1.0);
#ifdef PRTT_DISPLAY
  /* The scene's view transform; the colour buffer encodes sRGB (prtt_display.glsl). */
  FragColor.rgb = prtt_srgb_decode(prtt_display(FragColor.rgb, view.params.w));
#endif
}
