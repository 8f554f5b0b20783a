/* The traditional baselines: per-vertex transfer (from vertexTex, texel vidx),
 * shaded in the vertex stage by the same shade_point as the fragment modes;
 * the colour is interpolated across the triangle. No normal maps (a vertex
 * has one normal). */
void main()
{
  vec4 w = ModelMatrix * vec4(pos, 1.0);
  vec3 n = safe_normal(mat3(NormalMatrix) * nor, vec3(0.0, 0.0, 1.0));
  vec3 v = view_vector(w.xyz);

  vec3 albedo, spec;
  float exponent;
  surface_material(muv, albedo, spec, exponent);

  int index = int(vidx + 0.5);
  int width = textureSize(vertexTex, 0).x;
  ivec2 texel = ivec2(index % width, index / width);
  vec4 T4[SH_K4];
  for (int q = 0; q < SH_K4; q++) {
    T4[q] = texelFetch(vertexTex, ivec3(texel, q), 0);
  }
  vcolor = shade_point(T4, uv, n, v, albedo, spec, exponent) * view.params.x;
  gl_Position = prtt_clip(w);
}
