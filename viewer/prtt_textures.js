// PRTT's textures in the page: a glTF payload (KTX2: half floats, or 8 bits
// with a scale and offset per layer, Zstandard per level) checked against what
// the extension says it holds and the browser's limits, then turned into
// three.js array textures; the display table (the scene's view transform) as
// a 3D texture; the layer helpers the loader combines them with. Every
// problem is a PRTTError naming the input, shown on the page.
import * as THREE from 'three';
import { read as readKTX2 } from 'ktx-parse';
import { SHAPER_HI, SHAPER_LO } from './prtt_shaders.js';

const VK_FORMAT_R16G16B16A16_SFLOAT = 97;

const VK_FORMAT_R8G8B8A8_UNORM = 37;

const VK_FORMAT_R8_UNORM = 9;

const KTX2_ZSTD = 2;

/** The most one texture may unpack to in the page (a 4096^2 band-5 transfer is 896 MiB). */
export const MAX_TEXTURE_BYTES = 1024 * 2 ** 20;

/** The most a whole file's textures may unpack to in the page, checked from what the extension
 * declares before any is decoded (each texture is held on the CPU while it goes up, and on the GPU). */
export const MAX_SCENE_BYTES = 2048 * 2 ** 20;

/** Bytes the sets' textures unpack to, from the extension's declared layers and sizes alone
 * (half floats, 8 bytes a texel of a layer; shared glossy rows are expanded to three colours). */
export function declaredBytes(sets) {
  let total = 0;
  for (const s of Array.isArray(sets) ? sets : []) {
    for (const key of ['transfer', 'bounce', 'relightDC', 'relightGlossy']) {
      const p = s && s[key];
      if (!p || ![p.layers, p.width, p.height].every((v) => Number.isInteger(v) && v > 0)) continue;
      const copies = key === 'relightGlossy' && p.glossyColour === 'shared' ? 3 : 1;
      total += copies * p.layers * p.width * p.height * 8;
    }
    const m = s && s.sun;
    if (m && [m.width, m.height].every((v) => Number.isInteger(v) && v > 0)) {
      total += m.width * m.height * (m.format === 'RGBA16F' ? 8 : 1);
    }
    const lm = s && s.lamps;
    if (lm && [lm.width, lm.height].every((v) => Number.isInteger(v) && v > 0)) total += lm.width * lm.height * 4;
  }
  return total;
}

/** A problem with the file or the browser, said on the page (never a bare exception). */
export class PRTTError extends Error {}

/** The browser's limits that PRTT's textures and blocks meet. */
export function gpuLimits(renderer) {
  const gl = renderer.getContext();
  return {
    maxTextureSize: gl.getParameter(gl.MAX_TEXTURE_SIZE),
    maxArrayLayers: gl.getParameter(gl.MAX_ARRAY_TEXTURE_LAYERS),
    maxTextureUnits: gl.getParameter(gl.MAX_TEXTURE_IMAGE_UNITS),
    maxUniformBlockSize: gl.getParameter(gl.MAX_UNIFORM_BLOCK_SIZE),
    floatRenderTarget: !!gl.getExtension('EXT_color_buffer_float'),
    floatLinear: !!gl.getExtension('OES_texture_float_linear'),
  };
}

/** The KTX2 container of a payload's bytes (ktx-parse), or a PRTTError naming ``what``. */
function parseKTX2(bytes, what) {
  try {
    return readKTX2(bytes);
  } catch (e) {
    throw new PRTTError(`${what}: not a readable KTX2 file (${e.message})`);
  }
}

/**
 * The ``want`` bytes of KTX2 ``level`` of container ``c``: Zstandard-decoded
 * (its declared size checked first) or as stored; any other scheme or size
 * is a PRTTError naming ``what``.
 */
function levelBytes(c, level, want, zstd, what) {
  let data = level.levelData;
  if (c.supercompressionScheme === KTX2_ZSTD) {
    if (level.uncompressedByteLength !== want) {
      throw new PRTTError(`${what}: declares ${level.uncompressedByteLength} bytes, ${want} expected`);
    }
    try {
      data = zstd.decode(data, want);
    } catch (e) {
      throw new PRTTError(`${what}: damaged Zstandard data (${e.message || e})`);
    }
    if (data.byteLength !== want) {
      throw new PRTTError(`${what}: damaged Zstandard data (${data.byteLength} bytes decoded, ${want} expected)`);
    }
  } else if (c.supercompressionScheme !== 0) {
    throw new PRTTError(`${what}: supercompression scheme ${c.supercompressionScheme} is not PRTT's`);
  }
  if (data.byteLength !== want) throw new PRTTError(`${what}: ${data.byteLength} bytes, ${want} expected`);
  return data;
}

/**
 * One KTX2 payload as a half-float 2D array texture, checked against what
 * the extension says it holds (layers, size) and the browser's limits.
 * ``what`` names it in every message. Exported for the page reader's fuzz harness
 * (prtt_addon/dev/fuzz/page.py).
 */
export function arrayTexture(bytes, zstd, what, { layers, width, height, encoding = 'half', scale, offset }, limits) {
  const c = parseKTX2(bytes, what);
  const u8 = encoding === 'u8';
  if (!u8 && encoding !== 'half') throw new PRTTError(`${what}: unknown encoding ${encoding} (half or u8)`);
  const [vk, fmt] = u8 ? [VK_FORMAT_R8G8B8A8_UNORM, 'RGBA8'] : [VK_FORMAT_R16G16B16A16_SFLOAT, 'RGBA16F'];
  if (c.vkFormat !== vk || c.levels.length < 1) {
    throw new PRTTError(`${what}: not an ${fmt} array texture (vkFormat ${c.vkFormat})`);
  }
  if (u8 && !(Array.isArray(scale) && Array.isArray(offset) && scale.length === 4 * layers
      && offset.length === 4 * layers && [...scale, ...offset].every(Number.isFinite))) {
    throw new PRTTError(`${what}: an 8-bit payload needs ${4 * layers} finite scales and offsets`);
  }
  if (c.layerCount !== layers || c.pixelWidth !== width || c.pixelHeight !== height) {
    throw new PRTTError(`${what}: ${c.pixelWidth}x${c.pixelHeight} in ${c.layerCount} layers, the extension says `
      + `${width}x${height} in ${layers} (wrong coefficient count or a damaged file)`);
  }
  if (limits && (width > limits.maxTextureSize || height > limits.maxTextureSize)) {
    throw new PRTTError(`${what}: ${width}x${height} texels exceeds this browser's MAX_TEXTURE_SIZE `
      + `(${limits.maxTextureSize}); export a smaller bake`);
  }
  if (limits && layers > limits.maxArrayLayers) {
    throw new PRTTError(`${what}: ${layers} layers exceeds this browser's MAX_ARRAY_TEXTURE_LAYERS `
      + `(${limits.maxArrayLayers}); bake fewer bands`);
  }
  const level = c.levels[0];
  const want = width * height * layers * (u8 ? 4 : 8);
  if (want > MAX_TEXTURE_BYTES) {
    throw new PRTTError(`${what}: ${width}x${height} in ${layers} layers is ${(want / 2 ** 20).toFixed(0)} MiB, `
      + `over the viewer's ${MAX_TEXTURE_BYTES / 2 ** 20} MiB per texture`);
  }
  const data = levelBytes(c, level, want, zstd, what);
  if (u8) return halfArrayTexture(decodeU8(data, width * height, layers, scale, offset), width, height, layers);
  const half = new Uint16Array(data.buffer.slice(data.byteOffset, data.byteOffset + data.byteLength));
  return halfArrayTexture(half, width, height, layers);
}

/**
 * A set's sun mask (docs/gltf.md): a one-layer R8 KTX2, q / 255 the visible
 * fraction of the sun's disc per texel, or with sub-texel edges (format
 * RGBA16F) one RGBA16F KTX2 of (mask, d, valid, h), checked against the
 * extension's size and the browser's limits, as a 2D texture the GPU filters
 * bilinearly (prtt_shade.glsl sun_visible reads it: an R8 mask has b = 0); or
 * (format RGBA8) a set's lamp masks, channel i lamp i (lamp_light reads it).
 */
export function maskTexture(bytes, zstd, what, { width, height, format = 'R8' }, limits) {
  const c = parseKTX2(bytes, what);
  const edges = format === 'RGBA16F';
  const rgba8 = format === 'RGBA8';           // lamp masks: a lamp a channel
  if (!edges && !rgba8 && format !== 'R8') {
    throw new PRTTError(`${what}: unknown format ${format} (R8, RGBA8 or RGBA16F)`);
  }
  const vk = edges ? VK_FORMAT_R16G16B16A16_SFLOAT : rgba8 ? VK_FORMAT_R8G8B8A8_UNORM : VK_FORMAT_R8_UNORM;
  if (c.vkFormat !== vk || c.levels.length < 1) {
    throw new PRTTError(`${what}: not an ${format} texture (vkFormat ${c.vkFormat})`);
  }
  if (c.layerCount !== 1 || c.pixelWidth !== width || c.pixelHeight !== height) {
    throw new PRTTError(`${what}: ${c.pixelWidth}x${c.pixelHeight} in ${c.layerCount} layers, the extension says `
      + `${width}x${height} in 1 (a damaged file)`);
  }
  if (limits && (width > limits.maxTextureSize || height > limits.maxTextureSize)) {
    throw new PRTTError(`${what}: ${width}x${height} texels exceeds this browser's MAX_TEXTURE_SIZE `
      + `(${limits.maxTextureSize}); export a smaller bake`);
  }
  const want = width * height * (edges ? 8 : rgba8 ? 4 : 1);
  if (want > MAX_TEXTURE_BYTES) {
    throw new PRTTError(`${what}: ${width}x${height} is ${(want / 2 ** 20).toFixed(0)} MiB, `
      + `over the viewer's ${MAX_TEXTURE_BYTES / 2 ** 20} MiB per texture`);
  }
  const data = levelBytes(c, c.levels[0], want, zstd, what);
  let tex;
  if (edges) {
    const half = new Uint16Array(data.buffer.slice(data.byteOffset, data.byteOffset + data.byteLength));
    for (let t = 0; t < half.length; t++) {
      // a half with all exponent bits set is Inf or NaN: never a distance, a width or a fraction
      if ((half[t] & 0x7c00) === 0x7c00) throw new PRTTError(`${what}: a value that is not finite (a damaged file)`);
    }
    tex = new THREE.DataTexture(half, width, height, THREE.RGBAFormat, THREE.HalfFloatType);
  } else if (rgba8) {
    tex = new THREE.DataTexture(new Uint8Array(data), width, height, THREE.RGBAFormat, THREE.UnsignedByteType);
  } else {
    tex = new THREE.DataTexture(new Uint8Array(data), width, height, THREE.RedFormat, THREE.UnsignedByteType);
    tex.unpackAlignment = 1;
  }
  tex.minFilter = tex.magFilter = THREE.LinearFilter;
  tex.wrapS = tex.wrapT = THREE.ClampToEdgeWrapping;
  tex.generateMipmaps = false;
  tex.flipY = false;                 // the KTX2's first row is glTF's v = 0
  tex.colorSpace = THREE.NoColorSpace;
  tex.needsUpdate = true;
  return tex;
}

/**
 * Half floats of an 8-bit payload (docs/gltf.md): plane p = 4 layer + channel
 * holds offset[p] + scale[p] q, q = 0 .. 255; one 256-entry table per plane.
 */
function decodeU8(q, texels, layers, scale, offset) {
  const out = new Uint16Array(q.length);
  const lut = new Uint16Array(256 * 4 * layers);
  for (let p = 0; p < 4 * layers; p++) {
    for (let v = 0; v < 256; v++) lut[256 * p + v] = THREE.DataUtils.toHalfFloat(offset[p] + scale[p] * v);
  }
  for (let l = 0; l < layers; l++) {
    const base = l * texels * 4;
    for (let t = 0; t < texels * 4; t++) out[base + t] = lut[256 * (4 * l + (t & 3)) + q[base + t]];
  }
  return out;
}

function halfArrayTexture(half, width, height, layers) {
  const tex = new THREE.DataArrayTexture(half, width, height, layers);
  tex.type = THREE.HalfFloatType;
  tex.format = THREE.RGBAFormat;
  tex.minFilter = tex.magFilter = THREE.LinearFilter;
  tex.wrapS = tex.wrapT = THREE.ClampToEdgeWrapping;
  tex.generateMipmaps = false;
  tex.flipY = false;                 // the KTX2's first row is glTF's v = 0
  tex.colorSpace = THREE.NoColorSpace;
  tex.needsUpdate = true;
  return tex;
}

/**
 * The scene's view transform (AgX, Filmic, ...) as the export sampled it
 * from Blender: a Zstandard frame of a uint16 RGB table of size^3 (core/shading/display.py says the
 * conventions) -> a half-float 3D texture the GPU filters trilinearly, as
 * Blender's viewport does. The file is untrusted: every field is checked.
 */
export function displayTable(display, packed, zstd) {
  const t = display.table;
  const n = t.size;
  if (!Number.isInteger(n) || n < 2 || n > 129) throw new PRTTError(`display table: size ${n} is not 2..129`);
  if (t.encoding !== 'uint16-zstd') throw new PRTTError(`display table: encoding ${t.encoding} is not uint16-zstd`);
  if (!Array.isArray(t.shaper) || t.shaper[0] !== SHAPER_LO || t.shaper[1] !== SHAPER_HI) {
    throw new PRTTError(`display table: shaper ${JSON.stringify(t.shaper)} is not [${SHAPER_LO}, ${SHAPER_HI}] `
      + '(made by another PRTT version)');
  }
  const gamma = display.gamma ?? 1.0;
  if (!(Number.isFinite(gamma) && gamma > 0 && gamma <= 10)) throw new PRTTError(`display gamma ${gamma} is not in (0, 10]`);
  let bytes;
  try {
    bytes = zstd.decode(packed, n * n * n * 6);
  } catch (e) {
    throw new PRTTError(`display table: not a Zstandard frame of a ${n}^3 table (${e.message || e})`);
  }
  if (bytes.byteLength !== n * n * n * 6) {
    throw new PRTTError(`display table: not a Zstandard frame of a ${n}^3 table (${bytes.byteLength} bytes unpacked, `
      + `${n * n * n * 6} expected)`);
  }
  const view = new DataView(bytes.buffer, bytes.byteOffset, bytes.byteLength);
  const half = new Uint16Array(n * n * n * 4);
  const one = THREE.DataUtils.toHalfFloat(1.0);
  for (let i = 0; i < n * n * n; i++) {
    for (let c = 0; c < 3; c++) half[4 * i + c] = THREE.DataUtils.toHalfFloat(view.getUint16(6 * i + 2 * c, true) / 65535);
    half[4 * i + 3] = one;
  }
  const tex = new THREE.Data3DTexture(half, n, n, n);
  tex.type = THREE.HalfFloatType;
  tex.format = THREE.RGBAFormat;
  tex.minFilter = tex.magFilter = THREE.LinearFilter;
  tex.wrapS = tex.wrapT = tex.wrapR = THREE.ClampToEdgeWrapping;
  tex.generateMipmaps = false;
  tex.unpackAlignment = 1;
  tex.colorSpace = THREE.NoColorSpace;
  tex.needsUpdate = true;
  return { texture: tex, gammaInv: 1.0 / gamma, name: String(t.name || display.viewTransform) };
}

export function dummy2D() {
  const t = new THREE.DataTexture(new Float32Array([0, 0, 0, 1]), 1, 1, THREE.RGBAFormat, THREE.FloatType);
  t.needsUpdate = true;
  return t;
}

/**
 * The first K4 of every colour's fileK4 layers of a half-float array texture
 * (``colours`` groups of fileK4 layers), for a scene drawn with fewer bands
 * than its file: the shaders read coefficients k < K only.
 */
export function keepLayers(tex, colours, fileK4, K4) {
  if (K4 === fileK4) return tex;
  const { width, height, data } = tex.image;
  const per = width * height * 4;
  const out = new Uint16Array(per * K4 * colours);
  for (let c = 0; c < colours; c++) {
    out.set(data.subarray(c * fileK4 * per, (c * fileK4 + K4) * per), c * K4 * per);
  }
  tex.dispose();
  return halfArrayTexture(out, width, height, K4 * colours);
}

/**
 * Per-colour glossy rows from the shared ones (the EXRs' and the export's
 * layout under tuning auto), as core/io/exr_io.expand_shared_glossy makes
 * them: R_c = kappa_c S, kappa_c = dc_c,0 / mean_c dc_c,0 per texel (1 where
 * that mean is below 1e-3 of the largest colour's magnitude). ``dc``: the DC
 * rows (3 K4 layers), ``shared``: (Kg - 1) ceil(Kg / 4) layers. Half floats in,
 * half floats out (colour c's rows from layer c (Kg - 1) ceil(Kg / 4)).
 */
export function expandSharedGlossy(dc, K4, shared, kg) {
  const { width, height } = dc.image;
  const per = width * height * 4;
  const rows = (kg - 1) * Math.ceil(kg / 4);
  const S = shared.image.data, D = dc.image.data;
  const out = new Uint16Array(3 * rows * per);
  const f = THREE.DataUtils.fromHalfFloat, h = THREE.DataUtils.toHalfFloat;
  for (let t = 0; t < width * height; t++) {
    const d0 = [0, 1, 2].map((c) => f(D[c * K4 * per + 4 * t]));
    const m = (d0[0] + d0[1] + d0[2]) / 3;
    const big = Math.max(Math.abs(d0[0]), Math.abs(d0[1]), Math.abs(d0[2]));
    const kappa = d0.map((x) => (Math.abs(m) > 1e-3 * big ? Math.fround(x / m) : 1));
    for (let l = 0; l < rows; l++) {
      for (let j = 0; j < 4; j++) {
        const v = f(S[l * per + 4 * t + j]);
        for (let c = 0; c < 3; c++) out[(c * rows + l) * per + 4 * t + j] = h(Math.fround(kappa[c] * v));
      }
    }
  }
  shared.dispose();
  return halfArrayTexture(out, width, height, 3 * rows);
}

/** Concatenate half-float layer arrays (each a DataArrayTexture's Uint16Array). */
export function concatLayers(parts, width, height) {
  const n = parts.reduce((a, p) => a + p.image.depth, 0);
  const out = new Uint16Array(width * height * 4 * n);
  let at = 0;
  for (const p of parts) {
    out.set(p.image.data, at);
    at += p.image.data.length;
    p.dispose();
  }
  return halfArrayTexture(out, width, height, n);
}
