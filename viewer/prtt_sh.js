// PRTT's spherical-harmonic maths for the web page, in plain JavaScript (no
// imports: it loads in Node 20 and in a browser alike). Every function is a
// port of the Python core, which is the truth it is tested against
// (tests/test_viewer_sh.py):
//
//   shBasis          <-> prtt_addon.core.sh.basis.eval_basis (the recurrence of
//                        sh_eval in shaders/prtt_common.glsl, in float64)
//   gaussLegendre    <-> numpy.polynomial.legendre.leggauss
//   gauntNonzeros    <-> prtt_addon.core.sh.gaunt.sparse_gaunt (same order)
//   tpflMatrix       <-> prtt_addon.core.sh.gaunt.tpfl_matrix
//   lightBlock, relightBlock, gauntTable
//                    <-> prtt_addon.core.preview.pack.light_block,
//                        relight_block, gaunt_table
//   shRotation, rotateLight
//                    <-> prtt_addon.core.sh.rotation.sh_rotation, rotate
//   mappingRotation, composeLight, turnLightZ
//                    <-> prtt_addon.core.light.envmap.mapping_rotation,
//                        compose_light (+ environment_light's Z turn)
//   projectEquirect  <-> prtt_addon.core.light.envmap.project_equirect
//                        (method "area": exact pixel-patch integrals)
//
// Conventions (docs/sh-conventions.md): real orthonormal SH with the
// Condon-Shortley phase, flat index k = l*l + l + m, Blender's world frame
// (Z up). A light is an array of K = bands^2 [r, g, b] triples (coefficient
// first, as Python's (K, 3) arrays). Matrices are arrays of rows.

/** Largest band count of the Gaunt tensor (as gaunt.MAX_TENSOR_BANDS). */
export const MAX_TENSOR_BANDS = 16;
/** Largest band count projectEquirect accepts. */
export const MAX_PROJECT_BANDS = 8;
/** Most pixels projectEquirect accepts (64 Mi: a 11585 x 5792 equirect). */
export const MAX_PROJECT_PIXELS = 64 * 1024 * 1024;
/** Directions off unit length by more than this are refused (basis.UNIT_TOLERANCE). */
export const UNIT_TOLERANCE = 1e-5;

const SQRT2 = Math.sqrt(2.0);

function checkBands(bands, max, what = 'bands') {
  if (!Number.isInteger(bands) || bands < 1 || bands > max) {
    throw new Error(`${what} must be an integer in 1..${max}, got ${bands}`);
  }
  return bands;
}

/** (l, m) of the flat index k. */
function lmOf(k) {
  const l = Math.floor(Math.sqrt(k));
  return [l, k - l * l - l];
}

// --- basis ---------------------------------------------------------------------

const sectCache = new Map();
/** Pbar_m^m for m = 0..n-1 (basis.sectoral_constants). */
function sectoral(n) {
  let c = sectCache.get(n);
  if (!c) {
    c = new Float64Array(n);
    c[0] = Math.sqrt(1.0 / (4.0 * Math.PI));
    for (let m = 1; m < n; m++) c[m] = -Math.sqrt((2 * m + 1) / (2.0 * m)) * c[m - 1];
    sectCache.set(n, c);
  }
  return c;
}

/**
 * The recurrence of basis_unchecked at one unit direction, written into
 * out[offset .. offset + n*n). No checks (hot loops with unit directions).
 */
function basisInto(x, y, z, n, out, offset = 0) {
  const sect = sectoral(n);
  let cm = 1.0;   // Re (x + i y)^m
  let sm = 0.0;   // Im (x + i y)^m
  for (let m = 0; m < n; m++) {
    if (m > 0) {
      const c2 = x * cm - y * sm;
      sm = x * sm + y * cm;
      cm = c2;
    }
    let pPrev = sect[m];
    let pCur = 0.0;
    for (let l = m; l < n; l++) {
      let p;
      if (l === m) {
        p = pPrev;
      } else if (l === m + 1) {
        pCur = Math.sqrt(2 * m + 3) * z * pPrev;
        p = pCur;
      } else {
        const a = Math.sqrt((4.0 * l * l - 1.0) / (l * l - m * m));
        const b = Math.sqrt(((l - 1.0) ** 2 - m * m) / (4.0 * (l - 1.0) ** 2 - 1.0));
        p = a * (z * pCur - b * pPrev);
        pPrev = pCur;
        pCur = p;
      }
      const k0 = offset + l * l + l;
      if (m === 0) {
        out[k0] = p;
      } else {
        out[k0 + m] = (SQRT2 * p) * cm;
        out[k0 - m] = (SQRT2 * p) * sm;
      }
    }
  }
  return out;
}

/**
 * All K = bands^2 real SH at a unit direction (eval_basis).
 * @param {number[]} dir [x, y, z], unit length within UNIT_TOLERANCE (or any
 *   non-zero length with normalize = true)
 * @param {number} bands 1..64
 * @param {boolean} [normalize=false]
 * @returns {Float64Array} (K) y_k(dir), k = l*l + l + m
 */
export function shBasis(dir, bands, normalize = false) {
  checkBands(bands, 64);
  let [x, y, z] = dir;
  if (![x, y, z].every(Number.isFinite)) throw new Error(`direction is not finite: [${x}, ${y}, ${z}]`);
  const len = Math.sqrt(x * x + y * y + z * z);
  if (len < 1e-12) throw new Error(`direction has length ${len}: a zero vector has no direction`);
  if (normalize) {
    x /= len; y /= len; z /= len;
  } else if (Math.abs(len - 1.0) > UNIT_TOLERANCE) {
    throw new Error(`direction has length ${len}, not 1 (tolerance ${UNIT_TOLERANCE})`);
  }
  return basisInto(x, y, z, bands, new Float64Array(bands * bands));
}

// --- quadrature -------------------------------------------------------------------

/**
 * Gauss-Legendre nodes and weights on [-1, 1] (numpy's leggauss: ascending
 * nodes, symmetrised, weights summing to 2).
 * @param {number} n number of nodes, >= 1
 * @returns {{x: Float64Array, w: Float64Array}} each (n)
 */
export function gaussLegendre(n) {
  if (!Number.isInteger(n) || n < 1 || n > 4096) throw new Error(`gaussLegendre needs 1..4096 nodes, got ${n}`);
  const x = new Float64Array(n);
  const w = new Float64Array(n);
  for (let i = 0; i < n; i++) {
    // Node i (ascending): Newton on P_n from the asymptotic guess.
    let t = -Math.cos(Math.PI * (i + 0.75) / (n + 0.5));
    let dp = 1.0;
    for (let it = 0; it < 100; it++) {
      let p0 = 1.0, p1 = t;
      for (let k = 2; k <= n; k++) {
        const p2 = ((2 * k - 1) * t * p1 - (k - 1) * p0) / k;
        p0 = p1; p1 = p2;
      }
      const pn = n === 1 ? t : p1;
      const pm = n === 1 ? 1.0 : p0;
      dp = n * (t * pn - pm) / (t * t - 1.0);
      const step = pn / dp;
      t -= step;
      if (Math.abs(step) <= 1e-16 * Math.max(1.0, Math.abs(t))) break;
    }
    // Derivative at the converged node for the weight.
    let p0 = 1.0, p1 = t;
    for (let k = 2; k <= n; k++) {
      const p2 = ((2 * k - 1) * t * p1 - (k - 1) * p0) / k;
      p0 = p1; p1 = p2;
    }
    dp = n === 1 ? 1.0 : n * (t * p1 - p0) / (t * t - 1.0);
    x[i] = t;
    w[i] = 2.0 / ((1.0 - t * t) * dp * dp);
  }
  // Symmetrise and normalise as numpy does.
  const xs = new Float64Array(n), ws = new Float64Array(n);
  let sum = 0.0;
  for (let i = 0; i < n; i++) {
    xs[i] = (x[i] - x[n - 1 - i]) / 2;
    ws[i] = (w[i] + w[n - 1 - i]) / 2;
    sum += ws[i];
  }
  for (let i = 0; i < n; i++) ws[i] *= 2.0 / sum;
  return { x: xs, w: ws };
}

/** quadrature.gauss_sphere(degree) (phase 0.5): flat dirs (3Q) and weights (Q). */
function gaussSphere(degree) {
  const nz = Math.floor(degree / 2) + 1;
  const nphi = degree + 1;
  const { x: z, w: wz } = gaussLegendre(nz);
  const Q = nz * nphi;
  const dirs = new Float64Array(3 * Q);
  const w = new Float64Array(Q);
  const dphi = 2.0 * Math.PI / nphi;
  for (let a = 0; a < nz; a++) {
    const s = Math.sqrt(Math.max(1.0 - z[a] * z[a], 0.0));
    for (let b = 0; b < nphi; b++) {
      const phi = (b + 0.5) * dphi;
      const q = a * nphi + b;
      dirs[3 * q] = s * Math.cos(phi);
      dirs[3 * q + 1] = s * Math.sin(phi);
      dirs[3 * q + 2] = z[a];
      w[q] = wz[a] * dphi;
    }
  }
  return { dirs, w, Q };
}

// --- Gaunt tensor and the fixed-light product -----------------------------------------

const gauntCache = new Map();

/**
 * Non-zeros of the Gaunt tensor tau_ijk = integral y_i y_j y_k, computed by
 * exact quadrature (degree 3 (bands - 1)) and kept where the selection rules
 * allow, in sparse_gaunt's order (i, then j, then k ascending). Cached per
 * band count; do not modify the arrays.
 * @param {number} bands 1..16
 * @returns {{i: Int32Array, j: Int32Array, k: Int32Array, value: Float64Array, nnz: number, bands: number}}
 */
export function gauntNonzeros(bands) {
  const n = checkBands(bands, MAX_TENSOR_BANDS);
  const hit = gauntCache.get(n);
  if (hit) return hit;
  const K = n * n;
  const { dirs, w, Q } = gaussSphere(3 * (n - 1));
  // y[k * Q + q]: coefficient-major basis table.
  const y = new Float64Array(K * Q);
  const tmp = new Float64Array(K);
  for (let q = 0; q < Q; q++) {
    basisInto(dirs[3 * q], dirs[3 * q + 1], dirs[3 * q + 2], n, tmp, 0);
    for (let k = 0; k < K; k++) y[k * Q + q] = tmp[k];
  }
  const L = new Int32Array(K), M = new Int32Array(K);
  for (let k = 0; k < K; k++) [L[k], M[k]] = lmOf(k);
  const ii = [], jj = [], kk = [], vv = [];
  const wy = new Float64Array(Q);
  const wyy = new Float64Array(Q);
  for (let i = 0; i < K; i++) {
    for (let q = 0; q < Q; q++) wy[q] = w[q] * y[i * Q + q];
    for (let j = 0; j < K; j++) {
      let prepared = false;
      for (let k = 0; k < K; k++) {
        const li = L[i], lj = L[j], lk = L[k];
        if (lk < Math.abs(li - lj) || lk > li + lj || (li + lj + lk) % 2 !== 0) continue;
        const ai = Math.abs(M[i]), aj = Math.abs(M[j]), ak = Math.abs(M[k]);
        if (ak !== ai + aj && ak !== Math.abs(ai - aj)) continue;
        const neg = (M[i] < 0) + (M[j] < 0) + (M[k] < 0);
        if (neg % 2 !== 0) continue;
        if (!prepared) {
          for (let q = 0; q < Q; q++) wyy[q] = wy[q] * y[j * Q + q];
          prepared = true;
        }
        let s = 0.0;
        const yk = k * Q;
        for (let q = 0; q < Q; q++) s += wyy[q] * y[yk + q];
        ii.push(i); jj.push(j); kk.push(k); vv.push(s);
      }
    }
  }
  const out = {
    bands: n, nnz: vv.length,
    i: Int32Array.from(ii), j: Int32Array.from(jj), k: Int32Array.from(kk), value: Float64Array.from(vv),
  };
  gauntCache.set(n, out);
  return out;
}

function checkLight(L, K, what = 'light') {
  if (!Array.isArray(L) && !ArrayBuffer.isView(L)) throw new Error(`${what} must be an array of [r, g, b]`);
  if (L.length < K) throw new Error(`${what} has ${L.length} coefficients, ${K} needed`);
  for (let k = 0; k < K; k++) {
    const c = L[k];
    if (!c || c.length < 3 || !Number.isFinite(c[0]) || !Number.isFinite(c[1]) || !Number.isFinite(c[2])) {
      throw new Error(`${what}[${k}] is not a finite [r, g, b]`);
    }
  }
}

/**
 * Fixed-light product matrices M(L_c)[i][k] = sum_j tau_ijk L_j[c] (tpfl_matrix
 * of a (K, 3) light). Apply as Lp = M T (M is symmetric).
 * @param {number[][]} L K = bands^2 [r, g, b]
 * @param {number} bands 1..16
 * @returns {Float64Array[][]} 3 x K x K: [c][i] is row i (Float64Array(K)) of M(L_c)
 */
export function tpflMatrix(L, bands) {
  const n = checkBands(bands, MAX_TENSOR_BANDS);
  const K = n * n;
  checkLight(L, K);
  if (L.length !== K) throw new Error(`light has ${L.length} coefficients but bands=${n} needs ${K}`);
  const g = gauntNonzeros(n);
  const out = [];
  for (let c = 0; c < 3; c++) {
    const flat = new Float64Array(K * K);
    for (let e = 0; e < g.nnz; e++) flat[g.i[e] * K + g.k[e]] += g.value[e] * L[g.j[e]][c];
    const rows = [];
    for (let i = 0; i < K; i++) rows.push(flat.subarray(i * K, (i + 1) * K));
    out.push(rows);
  }
  return out;
}

// --- uniform blocks (pack.py) --------------------------------------------------------

/**
 * The PRTTLight uniform block (pack.light_block): for c = 0..2 and i < K the
 * row M(L_c)[i] padded to 4 ceil(K/4) floats, then the K coefficients as vec4
 * (r, g, b, 0). Uses the first K coefficients of L.
 * @param {number[][]} L >= K [r, g, b]
 * @param {number} bands
 * @returns {Float32Array} (3 K 4 K4 + 4 K), K4 = ceil(K / 4)
 */
export function lightBlock(L, bands) {
  const n = checkBands(bands, MAX_TENSOR_BANDS);
  const K = n * n;
  const K4 = Math.ceil(K / 4);
  const Lk = Array.from(L).slice(0, K);
  const M = tpflMatrix(Lk, n);
  const out = new Float32Array(3 * K * 4 * K4 + 4 * K);
  for (let c = 0; c < 3; c++) {
    for (let i = 0; i < K; i++) out.set(M[c][i], (c * K + i) * 4 * K4);
  }
  const base = 3 * K * 4 * K4;
  for (let k = 0; k < K; k++) {
    out[base + 4 * k] = Lk[k][0];
    out[base + 4 * k + 1] = Lk[k][1];
    out[base + 4 * k + 2] = Lk[k][2];
  }
  return out;
}

/**
 * The PRTTRelight uniform block (pack.relight_block): per colour c the light
 * in 4-coefficient groups (vec4 c K4 + q holds coefficients 4q..4q+3), zero
 * padded. Uses the first min(K, L.length) coefficients.
 * @param {number[][]} L [r, g, b] per coefficient
 * @param {number} bands
 * @returns {Float32Array} (3 * 4 K4)
 */
export function relightBlock(L, bands) {
  const n = checkBands(bands, 64);
  const K = n * n;
  const K4 = Math.ceil(K / 4);
  const used = Math.min(K, L.length);
  checkLight(L, used);
  const out = new Float32Array(3 * 4 * K4);
  for (let c = 0; c < 3; c++) {
    for (let k = 0; k < used; k++) out[c * 4 * K4 + k] = L[k][c];
  }
  return out;
}

/**
 * The Gaunt non-zeros as an RGBA float texture (pack.gaunt_table): texel e
 * (row e / width, column e % width) = (i, j, k, tau_ijk), zero padded.
 * @param {number} bands 1..16
 * @param {number} width texels per row
 * @returns {{data: Float32Array, rows: number, width: number, nnz: number}} data (rows * width * 4)
 */
export function gauntTable(bands, width) {
  if (!Number.isInteger(width) || width < 1) throw new Error(`width must be an integer >= 1, got ${width}`);
  const g = gauntNonzeros(bands);
  const rows = Math.max(1, Math.ceil(g.nnz / width));
  const data = new Float32Array(rows * width * 4);
  for (let e = 0; e < g.nnz; e++) {
    data[4 * e] = g.i[e];
    data[4 * e + 1] = g.j[e];
    data[4 * e + 2] = g.k[e];
    data[4 * e + 3] = g.value[e];
  }
  return { data, rows, width, nnz: g.nnz };
}

// --- rotation ------------------------------------------------------------------------

function checkRotation(R) {
  if (!Array.isArray(R) || R.length !== 3 || !R.every((r) => r && r.length === 3)) {
    throw new Error('rotation must be a 3x3 array of rows');
  }
  if (!R.every((r) => Array.from(r).every(Number.isFinite))) throw new Error('rotation matrix contains NaN or Inf');
  let err = 0.0;
  for (let i = 0; i < 3; i++) {
    for (let k = 0; k < 3; k++) {
      let s = 0.0;
      for (let j = 0; j < 3; j++) s += R[j][i] * R[j][k];
      err = Math.max(err, Math.abs(s - (i === k ? 1.0 : 0.0)));
    }
  }
  if (err > 1e-6) throw new Error(`matrix is not orthonormal (|R^T R - I| = ${err.toPrecision(3)})`);
  const det = R[0][0] * (R[1][1] * R[2][2] - R[1][2] * R[2][1])
    - R[0][1] * (R[1][0] * R[2][2] - R[1][2] * R[2][0])
    + R[0][2] * (R[1][0] * R[2][1] - R[1][1] * R[2][0]);
  if (det < 0) throw new Error('matrix is a reflection (det = -1), not a rotation');
}

/** rotation._ivanic_blocks for one rotation: per band l a (2l+1) x (2l+1) block (no CS phase). */
function ivanicBlocks(R, n) {
  const perm = [1, 2, 0];
  const r1 = perm.map((a) => perm.map((b) => R[a][b]));
  const blocks = [[[1.0]], r1];
  for (let l = 2; l < n; l++) {
    const prev = blocks[blocks.length - 1];
    const P = (i, a, b) => {
      const ri = r1[i + 1];
      if (b === l) return ri[2] * prev[a + l - 1][2 * l - 2] - ri[0] * prev[a + l - 1][0];
      if (b === -l) return ri[2] * prev[a + l - 1][0] + ri[0] * prev[a + l - 1][2 * l - 2];
      return ri[1] * prev[a + l - 1][b + l - 1];
    };
    const M = [];
    for (let m = -l; m <= l; m++) {
      const row = new Array(2 * l + 1).fill(0.0);
      const am = Math.abs(m);
      const d = m === 0 ? 1.0 : 0.0;
      for (let nn = -l; nn <= l; nn++) {
        const denom = Math.abs(nn) === l ? (2.0 * l) * (2 * l - 1) : (l + nn) * (l - nn);
        const u = Math.sqrt((l + m) * (l - m) / denom);
        const v = 0.5 * Math.sqrt((1 + d) * (l + am - 1) * (l + am) / denom) * (1 - 2 * d);
        const w = -0.5 * Math.sqrt(Math.max(0, (l - am - 1) * (l - am)) / denom) * (1 - d);
        let val = 0.0;
        if (u !== 0.0) val = val + u * P(0, m, nn);
        if (v !== 0.0) {
          let V;
          if (m === 0) {
            V = P(1, 1, nn) + P(-1, -1, nn);
          } else if (m > 0) {
            V = P(1, m - 1, nn) * Math.sqrt(1 + (m === 1 ? 1 : 0));
            if (m !== 1) V = V - P(-1, -m + 1, nn);
          } else {
            V = P(-1, -m - 1, nn) * Math.sqrt(1 + (m === -1 ? 1 : 0));
            if (m !== -1) V = V + P(1, m + 1, nn);
          }
          val = val + v * V;
        }
        if (w !== 0.0) {
          let W;
          if (m > 0) W = P(1, m + 1, nn) + P(-1, -m - 1, nn);
          else W = P(1, m - 1, nn) - P(-1, -m + 1, nn);
          val = val + w * W;
        }
        row[nn + l] = val;
      }
      M.push(row);
    }
    blocks.push(M);
  }
  return blocks.slice(0, n);
}

/**
 * Block-diagonal SH rotation D(R) (sh_rotation): g = D f for g(w) = f(R^T w).
 * @param {number[][]} R 3x3 proper rotation, rows (row-major nested arrays)
 * @param {number} bands 1..64
 * @returns {Float64Array[]} K rows of K
 */
export function shRotation(R, bands) {
  const n = checkBands(bands, 64);
  checkRotation(R);
  const blocks = ivanicBlocks(R, n);
  const K = n * n;
  const D = [];
  for (let k = 0; k < K; k++) D.push(new Float64Array(K));
  for (let l = 0; l < n; l++) {
    const lo = l * l;
    for (let a = -l; a <= l; a++) {
      for (let b = -l; b <= l; b++) {
        const s = ((Math.abs(a) + Math.abs(b)) % 2 === 0) ? 1.0 : -1.0;   // Condon-Shortley signs
        D[lo + a + l][lo + b + l] = blocks[l][a + l][b + l] * s;
      }
    }
  }
  return D;
}

function bandsOfLight(L) {
  const n = Math.round(Math.sqrt(L.length));
  if (n < 1 || n * n !== L.length) throw new Error(`a light has bands^2 coefficients; ${L.length} is not a square`);
  return n;
}

/**
 * The light turned by R (rotation.rotate(L, R) over the coefficient axis):
 * the coefficients of w -> L(R^T w).
 * @param {number[][]} L K [r, g, b]
 * @param {number[][]} R 3x3 rotation, rows
 * @returns {number[][]} K new [r, g, b]
 */
export function rotateLight(L, R) {
  const n = bandsOfLight(L);
  checkLight(L, n * n);
  const D = shRotation(R, n);
  const out = [];
  for (let l = 0; l < n; l++) {
    // D is block-diagonal: only band l's columns contribute to band l's rows.
    for (let a = l * l; a < (l + 1) * (l + 1); a++) {
      let r = 0.0, g = 0.0, b = 0.0;
      for (let c = l * l; c < (l + 1) * (l + 1); c++) {
        const d = D[a][c];
        r += d * L[c][0]; g += d * L[c][1]; b += d * L[c][2];
      }
      out.push([r, g, b]);
    }
  }
  return out;
}

/**
 * Blender's Euler XYZ rotation (radians), R = Rz Ry Rx (envmap.euler_xyz_matrix).
 * @returns {number[][]} 3x3 rows
 */
export function eulerXYZ(rx, ry, rz) {
  const cx = Math.cos(rx), sx = Math.sin(rx), cy = Math.cos(ry), sy = Math.sin(ry);
  const cz = Math.cos(rz), sz = Math.sin(rz);
  const Rx = [[1, 0, 0], [0, cx, -sx], [0, sx, cx]];
  const Ry = [[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]];
  const Rz = [[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]];
  return matmul3(matmul3(Rz, Ry), Rx);
}

function matmul3(A, B) {
  const C = [[0, 0, 0], [0, 0, 0], [0, 0, 0]];
  for (let i = 0; i < 3; i++) {
    for (let k = 0; k < 3; k++) C[i][k] = A[i][0] * B[0][k] + A[i][1] * B[1][k] + A[i][2] * B[2][k];
  }
  return C;
}

function transpose3(A) {
  return [0, 1, 2].map((i) => [A[0][i], A[1][i], A[2][i]]);
}

/**
 * The rotation a World's Mapping node applies to lookup directions (the image
 * is read at R w), envmap.mapping_rotation: its Euler XYZ rotation for type
 * 'POINT', the transpose for 'TEXTURE'.
 * @param {number[]} rotationXYZ [rx, ry, rz] radians
 * @param {'POINT'|'TEXTURE'} [vectorType='POINT']
 * @returns {number[][]} 3x3 rows
 */
export function mappingRotation(rotationXYZ, vectorType = 'POINT') {
  if (vectorType !== 'POINT' && vectorType !== 'TEXTURE') {
    throw new Error(`mapping vector type must be 'POINT' or 'TEXTURE', got ${vectorType}`);
  }
  const R = eulerXYZ(rotationXYZ[0], rotationXYZ[1], rotationXYZ[2]);
  return vectorType === 'POINT' ? R : transpose3(R);
}

/**
 * The world-frame light from an unrotated, unscaled projection
 * (envmap.compose_light): projection * strength, then, with a Mapping node's
 * lookupRotation R, rotated by R^T (the light seen along w is img(R w)).
 * @param {number[][]} projection K [r, g, b]
 * @param {number} [strength=1]
 * @param {number[][]|null} [lookupRotation=null] 3x3 rows
 * @returns {number[][]} K new [r, g, b]
 */
export function composeLight(projection, strength = 1.0, lookupRotation = null) {
  bandsOfLight(projection);
  checkLight(projection, projection.length, 'projection');
  const L = projection.map((c) => [c[0] * strength, c[1] * strength, c[2] * strength]);
  return lookupRotation ? rotateLight(L, transpose3(lookupRotation)) : L;
}

/**
 * The light as the World turned by `degrees` about Z: a Point-type Mapping
 * node with Z rotation `degrees` (composeLight(L, 1, mappingRotation([0, 0,
 * rad]))), done by mixing each band's (m, -m) pairs: for m > 0, with a the
 * angle in radians,
 *   c'(l, m)  = cos(m a) c(l, m)  + sin(m a) c(l, -m),
 *   c'(l, -m) = cos(m a) c(l, -m) - sin(m a) c(l, m).
 * (The environment appears turned by -degrees: lookups turn by +degrees.)
 * @param {number[][]} L K [r, g, b], unrotated
 * @param {number} degrees
 * @returns {number[][]} K new [r, g, b]
 */
export function turnLightZ(L, degrees) {
  const n = bandsOfLight(L);
  checkLight(L, n * n);
  const a = degrees * Math.PI / 180;
  const out = L.map((c) => [c[0], c[1], c[2]]);
  for (let l = 1; l < n; l++) {
    for (let m = 1; m <= l; m++) {
      const p = l * l + l + m, q = l * l + l - m;
      const c = Math.cos(m * a), s = Math.sin(m * a);
      for (let ch = 0; ch < 3; ch++) {
        out[p][ch] = c * L[p][ch] + s * L[q][ch];
        out[q][ch] = c * L[q][ch] - s * L[p][ch];
      }
    }
  }
  return out;
}

// --- equirect projection ------------------------------------------------------------

/**
 * Exact per-pixel integrals (envmap._area_tables): rows (H x K) of the theta
 * profile times sin theta integrated over each pixel row, cols (W x (2n-1))
 * of Phi_m integrated over each pixel column (m + n - 1 indexes the column).
 */
function areaTables(height, width, n) {
  const K = n * n;
  const q = n + 8;
  const { x, w: wq } = gaussLegendre(q);
  const half = 0.5 * Math.PI / height;
  const rows = new Float64Array(height * K);
  const y = new Float64Array(K);
  const prof = new Float64Array(q * K);
  for (let i = 0; i < height; i++) {
    const t0 = Math.PI * i / height;
    for (let j = 0; j < q; j++) {
      const theta = t0 + half * (x[j] + 1.0);
      const st = Math.sin(theta);
      // _theta_profile: y at phi = 0 (x = sin, y = 0, z = cos), m < 0 mirrored from m > 0.
      basisInto(st, 0.0, Math.cos(theta), n, y, 0);
      for (let l = 0; l < n; l++) {
        for (let m = -l; m <= l; m++) {
          const k = l * l + l + m;
          prof[j * K + k] = (m < 0 ? y[l * l + l - m] : y[k]) * st;
        }
      }
    }
    for (let k = 0; k < K; k++) {
      let s = 0.0;
      for (let j = 0; j < q; j++) s += prof[j * K + k] * (wq[j] * half);
      rows[i * K + k] = s;
    }
  }
  const nm = 2 * n - 1;
  const cols = new Float64Array(width * nm);
  for (let jx = 0; jx < width; jx++) {
    const pHi = Math.PI - 2.0 * Math.PI * jx / width;
    const pLo = pHi - 2.0 * Math.PI / width;
    for (let m = -(n - 1); m < n; m++) {
      let v;
      if (m === 0) v = pHi - pLo;
      else if (m > 0) v = (Math.sin(m * pHi) - Math.sin(m * pLo)) / m;
      else v = (Math.cos(-m * pLo) - Math.cos(-m * pHi)) / (-m);
      cols[jx * nm + m + n - 1] = v;
    }
  }
  return { rows, cols };
}

/**
 * Project an equirect environment to RGB SH with exact pixel-patch integrals
 * (envmap.project_equirect, method "area"), in float64. Orientation as
 * Blender's Environment Texture: the image centre looks along +X, u = 0.25
 * along +Y, row 0 (the first in memory) is +Z.
 * @param {Float32Array|Float64Array|number[]} data height * width * channels
 *   values, rows top first (file order), pixels left to right
 * @param {number} width
 * @param {number} height
 * @param {3|4} channels (a 4th, alpha, is ignored)
 * @param {number} bands 1..8
 * @returns {number[][]} K = bands^2 [r, g, b]. Negative values count as 0;
 *   NaN/Inf in r, g, b is an Error naming how many pixels have it.
 */
export function projectEquirect(data, width, height, channels, bands) {
  const n = checkBands(bands, MAX_PROJECT_BANDS);
  if (!Number.isInteger(width) || !Number.isInteger(height) || width < 1 || height < 1) {
    throw new Error(`environment image size must be positive integers, got ${width}x${height}`);
  }
  if (width * height > MAX_PROJECT_PIXELS) {
    throw new Error(`environment image is ${width}x${height} = ${width * height} pixels; `
      + `at most ${MAX_PROJECT_PIXELS} (64 Mi) are projected`);
  }
  if (channels !== 3 && channels !== 4) throw new Error(`environment image needs 3 or 4 channels, got ${channels}`);
  if (!data || data.length !== width * height * channels) {
    throw new Error(`environment data has ${data ? data.length : 0} values; `
      + `${width}x${height}x${channels} = ${width * height * channels} expected`);
  }
  let bad = 0;
  for (let p = 0, o = 0; p < width * height; p++, o += channels) {
    if (!Number.isFinite(data[o]) || !Number.isFinite(data[o + 1]) || !Number.isFinite(data[o + 2])) bad++;
  }
  if (bad) throw new Error(`environment image has ${bad} NaN/Inf pixels`);
  const K = n * n;
  const nm = 2 * n - 1;
  const { rows, cols } = areaTables(height, width, n);
  const mcol = new Int32Array(K);
  for (let k = 0; k < K; k++) mcol[k] = lmOf(k)[1] + n - 1;
  const out = new Float64Array(3 * K);
  const perM = new Float64Array(nm * 3);
  for (let h = 0; h < height; h++) {
    perM.fill(0.0);
    const rowBase = h * width * channels;
    for (let w = 0; w < width; w++) {
      const o = rowBase + w * channels;
      const r = Math.max(data[o], 0.0), g = Math.max(data[o + 1], 0.0), b = Math.max(data[o + 2], 0.0);
      if (r === 0.0 && g === 0.0 && b === 0.0) continue;
      const cb = w * nm;
      for (let m = 0; m < nm; m++) {
        const cw = cols[cb + m];
        perM[3 * m] += r * cw;
        perM[3 * m + 1] += g * cw;
        perM[3 * m + 2] += b * cw;
      }
    }
    const rb = h * K;
    for (let k = 0; k < K; k++) {
      const rk = rows[rb + k], m3 = 3 * mcol[k];
      out[3 * k] += rk * perM[m3];
      out[3 * k + 1] += rk * perM[m3 + 1];
      out[3 * k + 2] += rk * perM[m3 + 2];
    }
  }
  const L = [];
  for (let k = 0; k < K; k++) L.push([out[3 * k], out[3 * k + 1], out[3 * k + 2]]);
  return L;
}
