/* Vertex stage of the per-fragment modes (TPFL, TP, diffuse): world-space
 * attributes for the fragment stage. NormalMatrix is the inverse transpose of
 * ModelMatrix's 3x3 part; its [3][3] entry carries the sign of the model
 * determinant, which flips the bitangent of mirrored objects. */
void main()
{
  vec4 w = ModelMatrix * vec4(pos, 1.0);
  wpos = w.xyz;
  wnor = mat3(NormalMatrix) * nor;
  wtan = vec4(mat3(ModelMatrix) * tan.xyz, tan.w * NormalMatrix[3][3]);
  prtt_uv = uv;
  mat_uv = muv;
  nm_uv = nuv;
  gl_Position = prtt_clip(w);
}
