// The web host of PRTT's shading GLSL. The formulas live once, in the
// repository's shaders/*.glsl, which Blender's viewport compiles through
// GPUShaderCreateInfo (prtt_addon/core/preview/shader_source.py describes
// each variant: files, defines, resources). This module describes the same
// variants (tests/test_viewer_shaders.py checks them against shader_source.py)
// and writes the declarations Blender's create-info would write, for WebGL2
// (GLSL ES 3.00), around the very same files:
//   - uniform blocks `view`, `material`, `light`, `relight` (std140, vec4/mat4
//     members only) as named blocks PRTTViewBlock, ...;
//   - Blender's push constants ModelMatrix / NormalMatrix from three's
//     modelMatrix, turned into the bake frame (Z up) by gltfToBakeFrame, so
//     the shared code sees Blender's world frame;
//   - the fragment output FragColor as a plain variable: the host's own
//     main() runs the shared main() and writes sRGB (the 8-bit canvas shows
//     what `prtt render` writes to a PNG).
// Pure: no three.js import, so Node runs it too (the tests do).

export const MODES = ['tpfl', 'tp', 'diffuse'];
export const MAX_PREVIEW_BANDS = 8;
export const GAUNT_WIDTH = 1024;
// The display table's shaper range in stops (core/shading/display.py).
export const SHAPER_LO = -12.0;
export const SHAPER_HI = 12.0;

const TYPEDEFS = (tpfl, k) => `
struct PRTTView {
  mat4 view_projection;
  vec4 camera;
  vec4 params;
};
struct PRTTMaterial {
  vec4 base;
  vec4 params;
};
struct PRTTLight {
  vec4 tpfl[${tpfl}];
  vec4 coeffs[${k}];
};
`;

// The sun's block (shader_source.SUN_TYPEDEFS): direction (xyz towards it,
// w = angle^2 / 16), irradiance (rgb W/m^2 facing it).
const SUN_TYPEDEFS = `
struct PRTTSun {
  vec4 direction;
  vec4 irradiance;
};
`;

// The lamps' block (shader_source.LAMP_TYPEDEFS): info (x the count), per lamp
// position (xyz, w radius), intensity (rgb W/sr, w the spot's smoothstep scale),
// spot (xyz axis, w cos half the cone; -2 for a point).
const LAMP_TYPEDEFS = `
struct PRTTLamps {
  vec4 info;
  vec4 position[4];
  vec4 intensity[4];
  vec4 spot[4];
};
`;

const RELIGHT_TYPEDEFS = (n) => `
struct PRTTRelight {
  vec4 light[${n}];
};
`;

export function shSizes(bands) {
  const k = bands * bands;
  return [k, Math.ceil(k / 4)];
}

/**
 * The surface shader of a fragment mode: the same description as
 * shader_source.variant(mode, bands, bounce=..., display=..., sun=...) for
 * the fragment modes. gauntNnz: the Gaunt tensor's non-zero count (TP
 * only). display: ending in the file's view transform (prtt_display.glsl;
 * SHAPER_LO/HI as core/shading/display.py), decoded back for the sRGB
 * encode of main(). sun: adding the sun's direct light with its mask
 * (PRTT_SUN: the sampler sunTex, the block PRTTSun sun). lamps: adding point
 * and spot lamps' direct light with their masks (PRTT_LAMPS: the sampler
 * lampTex, the block PRTTLamps lamps).
 */
export function surfaceVariant(mode, bands, { bounce = false, gauntNnz = 0, display = false, sun = false,
  lamps = false } = {}) {
  if (!MODES.includes(mode)) throw new Error(`unknown mode ${mode}; use one of ${MODES.join(', ')}`);
  if (!(Number.isInteger(bands) && bands >= 1 && bands <= MAX_PREVIEW_BANDS)) {
    throw new Error(`the preview supports 1 to ${MAX_PREVIEW_BANDS} SH bands, got ${bands}`);
  }
  const [k, k4] = shSizes(bands);
  const defines = [['SH_BANDS', String(bands)], ['SH_K', String(k)], ['SH_K4', String(k4)]];
  const triple = mode === 'tp';
  if (triple) {
    defines.push(['PRTT_TRIPLE_PRODUCT', '1'], ['GAUNT_NNZ', String(gauntNnz)], ['GAUNT_WIDTH', String(GAUNT_WIDTH)]);
  }
  if (mode === 'diffuse') defines.push(['PRTT_DIFFUSE', '1']);
  if (bounce) defines.push(['PRTT_BOUNCE', '1']);
  if (sun) defines.push(['PRTT_SUN', '1']);
  if (lamps) defines.push(['PRTT_LAMPS', '1']);
  if (display) defines.push(['PRTT_DISPLAY', '1'], ['PRTT_SHAPER_LO', SHAPER_LO.toFixed(1)], ['PRTT_SHAPER_HI', SHAPER_HI.toFixed(1)]);
  const samplers = [[1, 'FLOAT_2D', 'baseTex'], [2, 'FLOAT_2D', 'roughTex']];
  if (bounce) samplers.push([4, 'FLOAT_2D_ARRAY', 'bounceTex']);
  if (triple) samplers.push([5, 'FLOAT_2D', 'gauntTex']);
  samplers.push([0, 'FLOAT_2D_ARRAY', 'transferTex'], [3, 'FLOAT_2D', 'normalTex']);
  if (sun) samplers.push([8, 'FLOAT_2D', 'sunTex']);
  if (lamps) samplers.push([9, 'FLOAT_2D', 'lampTex']);
  if (display) samplers.push([7, 'FLOAT_3D', 'displayLut']);
  samplers.sort((a, b) => a[0] - b[0]);
  const lib = ['prtt_common.glsl', 'prtt_view.glsl', 'prtt_light.glsl', 'prtt_layering.glsl', 'prtt_shade.glsl'];
  return {
    name: `prtt_${mode}_b${bands}${bounce ? '_bounce' : ''}${display ? '_display' : ''}${sun ? '_sun' : ''}${lamps ? '_lamps' : ''}`,
    defines,
    typedefs: TYPEDEFS(3 * k * k4, k) + (sun ? SUN_TYPEDEFS : '') + (lamps ? LAMP_TYPEDEFS : ''),
    vertexIn: [[0, 'VEC3', 'pos'], [1, 'VEC3', 'nor'], [2, 'VEC2', 'uv'], [3, 'VEC2', 'muv'], [4, 'VEC2', 'nuv'],
      [5, 'VEC4', 'tan']],
    interface: [['smooth', 'VEC3', 'wpos'], ['smooth', 'VEC3', 'wnor'], ['smooth', 'VEC4', 'wtan'],
      ['smooth', 'VEC2', 'prtt_uv'], ['smooth', 'VEC2', 'mat_uv'], ['smooth', 'VEC2', 'nm_uv']],
    samplers,
    uniformBufs: [[0, 'PRTTView', 'view'], [1, 'PRTTMaterial', 'material'], [2, 'PRTTLight', 'light'],
      ...(sun ? [[3, 'PRTTSun', 'sun']] : []), ...(lamps ? [[4, 'PRTTLamps', 'lamps']] : [])],
    pushConstants: [['MAT4', 'ModelMatrix'], ['MAT4', 'NormalMatrix']],
    vertexFiles: ['prtt_view.glsl', 'prtt_surface_vert.glsl'],
    fragmentFiles: [...lib, ...(display ? ['prtt_display.glsl'] : []), 'prtt_surface_frag.glsl'],
  };
}

/** The depth pre-pass, as shader_source.depth_variant(): the shading pass's clip positions. */
export function depthVariant() {
  return {
    name: 'prtt_depth',
    defines: [],
    typedefs: TYPEDEFS(1, 1),
    vertexIn: [[0, 'VEC3', 'pos']],
    interface: [],
    samplers: [],
    uniformBufs: [[0, 'PRTTView', 'view']],
    pushConstants: [['MAT4', 'ModelMatrix']],
    vertexFiles: ['prtt_view.glsl', 'prtt_depth_vert.glsl'],
    fragmentFiles: ['prtt_depth_frag.glsl'],
  };
}

/** The relight pass, as shader_source.relight_variant(bands, glossyBands, shared). */
export function relightVariant(bands, glossyBands, shared = false) {
  const [k, k4] = shSizes(bands);
  const kg = glossyBands * glossyBands;
  const tinted = Boolean(shared && glossyBands);
  return {
    name: `prtt_relight_b${bands}_g${glossyBands}` + (tinted ? '_shared' : ''),
    defines: [['SH_K', String(k)], ['SH_K4', String(k4)], ['RELIGHT_KG', String(Math.max(kg, 1))],
      ['RELIGHT_KG4', String(Math.max(Math.ceil(kg / 4), 1))], ...(tinted ? [['RELIGHT_SHARED', '1']] : [])],
    typedefs: RELIGHT_TYPEDEFS(3 * k4),
    vertexIn: [[0, 'VEC2', 'pos']],
    interface: [],
    samplers: [[0, 'FLOAT_2D_ARRAY', 'relightTex']],
    uniformBufs: [[0, 'PRTTRelight', 'relight']],
    pushConstants: [['INT', 'out_colour'], ['INT', 'out_q']],
    vertexFiles: ['prtt_relight_vert.glsl'],
    fragmentFiles: ['prtt_relight_frag.glsl'],
  };
}

const GLSL_TYPE = { FLOAT: 'float', VEC2: 'vec2', VEC3: 'vec3', VEC4: 'vec4', MAT4: 'mat4', INT: 'int' };
const SAMPLER_TYPE = { FLOAT_2D: 'sampler2D', FLOAT_2D_ARRAY: 'sampler2DArray', FLOAT_3D: 'sampler3D' };

/** The uniform block name three.js binds a UniformsGroup to (group.name). */
export const blockName = (struct) => `${struct}Block`;

function header(v) {
  const lines = ['precision highp float;', 'precision highp int;', 'precision highp sampler2D;',
    'precision highp sampler2DArray;', 'precision highp sampler3D;'];
  for (const [name, value] of v.defines) lines.push(`#define ${name} ${value}`);
  lines.push(v.typedefs);
  for (const [, struct, name] of v.uniformBufs) {
    lines.push(`layout(std140) uniform ${blockName(struct)} { ${struct} ${name}; };`);
  }
  for (const [, type, name] of v.samplers) lines.push(`uniform ${SAMPLER_TYPE[type]} ${name};`);
  return lines;
}

/** mat4 (column-major GLSL constructor) of the 3x3 row-major rotation m. */
function mat4Literal(m) {
  const c = (i, j) => Number(m[j][i]).toFixed(1);
  return `mat4(${c(0, 0)}, ${c(0, 1)}, ${c(0, 2)}, 0.0, ${c(1, 0)}, ${c(1, 1)}, ${c(1, 2)}, 0.0, `
    + `${c(2, 0)}, ${c(2, 1)}, ${c(2, 2)}, 0.0, 0.0, 0.0, 0.0, 1.0)`;
}

/**
 * GLSL ES 3.00 sources {vertexShader, fragmentShader} (without #version,
 * which three.js adds for GLSL3) of a surface (or the depth) variant around the shared
 * files' texts (read(name) -> source), for three.js's RawShaderMaterial.
 * gltfToBake: the 3x3 glTF -> bake frame rotation of the extension (its
 * entries are 0 and +-1).
 */
export function surfaceSources(v, read, gltfToBake) {
  for (const row of gltfToBake) {
    for (const x of row) if (![0, 1, -1].includes(x)) throw new Error('gltfToBakeFrame must be an axis permutation');
  }
  const vs = header(v);
  // the depth pre-pass and the shading pass must agree to the bit on every depth
  vs.push('invariant gl_Position;');
  vs.push('uniform mat4 modelMatrix;   // three.js: the node\'s world matrix, glTF frame');
  vs.push(`const mat4 PRTT_GLTF_TO_BAKE = ${mat4Literal(gltfToBake)};`);
  vs.push('#define ModelMatrix (PRTT_GLTF_TO_BAKE * modelMatrix)');
  vs.push(`mat4 prtt_normal_matrix() {
  mat3 m = mat3(ModelMatrix);
  float d = determinant(m);
  mat4 n = abs(d) > 1e-30 ? mat4(transpose(inverse(m))) : mat4(1.0);
  n[3][3] = d < 0.0 ? -1.0 : 1.0;
  return n;
}`);
  vs.push('#define NormalMatrix prtt_normal_matrix()');
  for (const [, type, name] of v.vertexIn) vs.push(`in ${GLSL_TYPE[type]} ${name};`);
  for (const [interp, type, name] of v.interface) vs.push(`${interp} out ${GLSL_TYPE[type]} ${name};`);
  for (const f of v.vertexFiles) vs.push(read(f));
  const fs = header(v);
  for (const [interp, type, name] of v.interface) fs.push(`${interp} in ${GLSL_TYPE[type]} ${name};`);
  fs.push('layout(location = 0) out vec4 prtt_frag_out;', 'vec4 FragColor;', '#define main prtt_main');
  for (const f of v.fragmentFiles) fs.push(read(f));
  fs.push('#undef main', `vec3 prtt_srgb(vec3 c) {
  c = clamp(c, 0.0, 1.0);
  return mix(12.92 * c, 1.055 * pow(c, vec3(1.0 / 2.4)) - 0.055, step(vec3(0.0031308), c));
}
void main() {
  prtt_main();
  prtt_frag_out = vec4(prtt_srgb(FragColor.rgb), 1.0);
}`);
  return { vertexShader: vs.join('\n'), fragmentShader: fs.join('\n') };
}

/** The relight pass's sources: it writes linear floats to a float render target. */
export function relightSources(v, read) {
  const vs = header(v);
  for (const [, type, name] of v.vertexIn) vs.push(`in ${GLSL_TYPE[type]} ${name};`);
  for (const f of v.vertexFiles) vs.push(read(f));
  const fs = header(v);
  for (const [type, name] of v.pushConstants) fs.push(`uniform ${GLSL_TYPE[type]} ${name};`);
  fs.push('layout(location = 0) out vec4 FragColor;');
  for (const f of v.fragmentFiles) fs.push(read(f));
  return { vertexShader: vs.join('\n'), fragmentShader: fs.join('\n') };
}

/** Every shaders/ file a variant needs, fetched once (relative to this module). */
export async function fetchSources(files, base = new URL('../shaders/', import.meta.url)) {
  const out = {};
  await Promise.all([...new Set(files)].map(async (f) => {
    const r = await fetch(new URL(f, base));
    if (!r.ok) throw new Error(`shaders/${f}: HTTP ${r.status} (serve the repository, shaders/ included)`);
    out[f] = await r.text();
  }));
  return (name) => {
    if (!(name in out)) throw new Error(`shaders/${name} was not fetched`);
    return out[name];
  };
}
