/* The upload pass: one layer of a 2D array texture from a 2D texture of the
 * same size (blender/preview/renderer.py uploads a texture a layer at a time,
 * so the CPU holds one layer, not the whole texture). Texel for texel: the
 * quad covers the layer exactly, texelFetch reads without filtering. */
void main()
{
  FragColor = texelFetch(layerTex, ivec2(gl_FragCoord.xy), 0);
}
