/* Transferred incident radiance (cosine-weighted, per colour channel) from the
 * transfer T and the World light, contracted with the glossy weights w as it
 * is produced (docs/shading.md), so no K-long RGB array is kept per pixel:
 *   dc     = Lp_0
 *   glossy = sum_k w_k Lp_k
 * with
 *   TPFL:    Lp_c = M(L_c) T, one dot(vec4, vec4) per 4 coefficients  (O(K^2))
 *   TP:      Lp_c,k = sum over the Gaunt tensor's non-zeros tau_ijk T_i L_c,j
 *   diffuse: only the double product T . L_c = sqrt(4 pi) Lp_0 is needed (O(K))
 * Needs the uniform block `light` (struct PRTTLight) and, for TP, `gauntTex`.
 */

/* The outer loop's bound comes from the view block (view.params.z = SH_K) on
 * purpose: with a compile-time bound, shader compilers unroll all K * K4 dot
 * products, which costs llvmpipe 10-30 s per shader and buys a GPU nothing
 * (the inner loop stays unrolled, the light rows stay in the uniform cache). */
void tpfl_contract(vec4 T4[SH_K4], float w[SH_K], out vec3 dc, out vec3 glossy)
{
  glossy = vec3(0.0);
  dc = vec3(0.0);
  int n = int(view.params.z + 0.5);   /* == SH_K; the renderer sets it */
  for (int i = 0; i < n; i++) {
    vec3 lp = vec3(0.0);
    for (int q = 0; q < SH_K4; q++) {
      lp.r += dot(light.tpfl[(0 * SH_K + i) * SH_K4 + q], T4[q]);
      lp.g += dot(light.tpfl[(1 * SH_K + i) * SH_K4 + q], T4[q]);
      lp.b += dot(light.tpfl[(2 * SH_K + i) * SH_K4 + q], T4[q]);
    }
    if (i == 0) {
      dc = lp;
    }
    glossy += w[i] * lp;
  }
}

#ifdef PRTT_TRIPLE_PRODUCT
/* gauntTex texel e = (i, j, k, tau_ijk), row-major in a GAUNT_WIDTH-wide texture. */
void tp_contract(vec4 T4[SH_K4], float w[SH_K], out vec3 dc, out vec3 glossy)
{
  vec3 Lp[SH_K];
  for (int k = 0; k < SH_K; k++) {
    Lp[k] = vec3(0.0);
  }
  for (int e = 0; e < GAUNT_NNZ; e++) {
    vec4 g = texelFetch(gauntTex, ivec2(e % GAUNT_WIDTH, e / GAUNT_WIDTH), 0);
    int i = int(g.x);
    int j = int(g.y);
    int k = int(g.z);
    Lp[k] += (g.w * sh_coef(T4, i)) * light.coeffs[j].rgb;
  }
  dc = Lp[0];
  glossy = vec3(0.0);
  for (int k = 0; k < SH_K; k++) {
    glossy += w[k] * Lp[k];
  }
}
#endif

/* T . L_c: the double product of the diffuse fast path. */
vec3 diffuse_dot(vec4 T4[SH_K4])
{
  vec3 acc = vec3(0.0);
  for (int k = 0; k < SH_K; k++) {
    acc += sh_coef(T4, k) * light.coeffs[k].rgb;
  }
  return acc;
}
