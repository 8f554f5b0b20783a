/* Vertex baselines: the interpolated per-vertex colour. */
void main()
{
  FragColor = vec4(vcolor, 1.0);
}
