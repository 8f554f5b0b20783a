/* Depth pre-pass: the same clip position as the shading pass (prtt_clip), so
 * the shading pass can test with LESS_EQUAL and shade each pixel once. */
void main()
{
  gl_Position = prtt_clip(ModelMatrix * vec4(pos, 1.0));
}
