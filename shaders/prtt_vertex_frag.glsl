/* Vertex baselines: the interpolated per-vertex colour. */
void main()
{
  FragColor = vec4(vcolor, 1.0);
#ifdef PRTT_DISPLAY
  /* The scene's view transform per pixel; the colour buffer encodes sRGB (prtt_display.glsl). */
  FragColor.rgb = prtt_srgb_decode(prtt_display(FragColor.rgb, view.params.w));
#endif
}
