/* The relight pass (bounce_mode "relightable", docs/shading.md): one layer of
 * the bounce texture, B_c,o = sum_i R_c,o,i L_c,i, for colour out_colour and
 * coefficients o = 4 out_q .. 4 out_q + 3. relightTex holds the operator
 * (core/preview/pack.py, pack_relight_operator): the DC rows (layers
 * c * SH_K4 + l), then per colour and out coefficient o = 1 .. RELIGHT_KG - 1
 * the glossy rows (RELIGHT_KG4 layers each); padding is zero, so whole vec4
 * dot products are exact. With RELIGHT_SHARED the glossy rows are stored
 * once for all colours (tuning auto, pack.relight_operator_layers(expand=
 * False): a third of the layers) and tinted here per texel as
 * core/io/exr_io.expand_shared_glossy tints them on the CPU:
 * kappa_c = d0_c / mean(d0), 1 where |mean| <= 1e-3 max |d0_c|, d0_c the
 * colour's DC response to the light's DC. */
float relight_tint(ivec2 p, int c)
{
  vec3 d0 = vec3(texelFetch(relightTex, ivec3(p, 0), 0).x, texelFetch(relightTex, ivec3(p, SH_K4), 0).x,
                 texelFetch(relightTex, ivec3(p, 2 * SH_K4), 0).x);
  float m = (d0.x + d0.y + d0.z) / 3.0;
  float big = max(abs(d0.x), max(abs(d0.y), abs(d0.z)));
  return abs(m) > 1e-3 * big ? d0[c] / m : 1.0;
}

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
#ifdef RELIGHT_SHARED
      int base = 3 * SH_K4 + (o - 1) * RELIGHT_KG4;
#else
      int base = 3 * SH_K4 + (out_colour * (RELIGHT_KG - 1) + (o - 1)) * RELIGHT_KG4;
#endif
      for (int l = 0; l < RELIGHT_KG4; l++) {
        acc += dot(texelFetch(relightTex, ivec3(p, base + l), 0), relight.light[out_colour * SH_K4 + l]);
      }
#ifdef RELIGHT_SHARED
      acc *= relight_tint(p, out_colour);
#endif
    }
    result[j] = acc;
  }
  FragColor = result;
}
