/* The relight pass (bounce_mode "relightable", docs/shading.md): one layer of
 * the bounce texture, B_c,o = sum_i R_c,o,i L_c,i, for colour out_colour and
 * coefficients o = 4 out_q .. 4 out_q + 3. relightTex holds the operator
 * (core/preview/pack.py, pack_relight_operator): the DC rows (layers
 * c * SH_K4 + l), then per colour and out coefficient o = 1 .. RELIGHT_KG - 1
 * the glossy rows (RELIGHT_KG4 layers each); padding is zero, so whole vec4
 * dot products are exact. */
void main()
{
  ivec2 p = ivec2(gl_FragCoord.xy);
  vec4 result = vec4(0.0);
  for (int j = 0; j < 4; j++) {
    int o = 4 * out_q + j;
    float acc = 0.0;
    if (o == 0) {
      for (int l = 0; l < SH_K4; l++) {
        acc += dot(texelFetch(relightTex, ivec3(p, out_colour * SH_K4 + l), 0), relight.light[out_colour * SH_K4 + l]);
      }
    }
    else if (o < RELIGHT_KG) {
      int base = 3 * SH_K4 + (out_colour * (RELIGHT_KG - 1) + (o - 1)) * RELIGHT_KG4;
      for (int l = 0; l < RELIGHT_KG4; l++) {
        acc += dot(texelFetch(relightTex, ivec3(p, base + l), 0), relight.light[out_colour * SH_K4 + l]);
      }
    }
    result[j] = acc;
  }
  FragColor = result;
}
