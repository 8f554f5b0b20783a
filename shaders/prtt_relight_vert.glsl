/* The relight pass: a quad over the whole bounce texture layer. */
void main()
{
  gl_Position = vec4(pos, 0.0, 1.0);
}
