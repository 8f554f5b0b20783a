/* Positions and view vectors, shared by every vertex stage so that the depth
 * pre-pass and the shading pass compute bit-identical depths.
 * Needs the uniform block `view` (struct PRTTView). */

vec4 prtt_clip(vec4 world)
{
  vec4 p = view.view_projection * world;
  /* The viewport draws over Blender's own depth: a tiny bias towards the eye
   * (0 offscreen) keeps our surfaces in front of Blender's copy of them. */
  p.z -= view.params.y * p.w;
  return p;
}

/* Unit vector from the surface point towards the eye. */
vec3 view_vector(vec3 wpos)
{
  if (view.camera.w > 0.5) {
    vec3 d = view.camera.xyz - wpos;
    float l2 = dot(d, d);
    return (l2 > 0.0) ? d * inversesqrt(l2) : vec3(0.0, 0.0, 1.0);
  }
  return view.camera.xyz; /* orthographic: one direction for every pixel */
}
