/* Depth pre-pass: colour writes are masked off. */
void main()
{
  FragColor = vec4(0.0);
}
