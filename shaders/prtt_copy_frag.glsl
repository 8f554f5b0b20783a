/* The upload pass: one band of rows of one layer of a 2D array texture from
 * a 2D texture holding just those rows (blender/preview/renderer.py uploads a
 * texture a band of rows of a layer at a time, so the CPU holds one band,
 * not the texture). The viewport covers the band's rows, row0 the first of
 * them; texel for texel: texelFetch reads without filtering. */
void main()
{
  FragColor = texelFetch(layerTex, ivec2(gl_FragCoord.xy) - ivec2(0, row0), 0);
}
