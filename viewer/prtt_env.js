// An environment image's bytes -> its SH light, in the page: OpenEXR through
// three's EXRLoader, Radiance .hdr by a port of the Python reader
// (prtt_addon/core/io/image_io.read_hdr_image), then projectEquirect
// (prtt_sh.js, = envmap.project_equirect). tests/test_viewer_sh.py checks the
// result against Python on Blender's forest.exr and on written .hdr files.
//
// Row order: EXRLoader returns rows bottom first (its texture has flipY =
// false), so they are flipped here to the file order projectEquirect takes
// (row 0 = top = +Z). three's HDRLoader is not used: it decodes RGBE as
// m / 255 * 2^(e - 128), where Radiance (and the Python reader) use
// (m + 0.5) / 256 * 2^(e - 128) — up to 0.2 % apart on bright channels and
// several % on dim ones — and it reads neither "+Y" (bottom-up) files nor
// checks a size before allocating.
//
// three is imported when an EXR is first decoded, not at the top: this module
// also runs in a Web Worker (prtt_env_worker.js, where the page decodes what a
// user drops), and import maps do not reach workers, so there the worker hands
// in three and EXRLoader itself (useExrModules).
import { MAX_PROJECT_BANDS, MAX_PROJECT_PIXELS, projectEquirect } from './prtt_sh.js';

let exrModules = null;
let loadExrModules = async () => {
  const [THREE, { EXRLoader }] = await Promise.all([import('three'), import('three/addons/loaders/EXRLoader.js')]);
  return { THREE, EXRLoader };
};

/** Decode EXR with the {THREE, EXRLoader} that `load` (async) gives, loaded at the first EXR (a worker's). */
export function useExrModules(load) {
  loadExrModules = load;
  exrModules = null;
}

async function exrLoader() {
  if (!exrModules) exrModules = await loadExrModules();
  return exrModules;
}

/** Most pixels a side of an environment image (image_io.MAX_ENV_SIDE). */
export const MAX_ENV_SIDE = 1 << 15;
/** Most pixels in all (the projection's bound; Python's reader allows 2^28). */
export const MAX_ENV_PIXELS = MAX_PROJECT_PIXELS;
/** Bytes of a Radiance header before its resolution line (image_io.MAX_HDR_HEADER). */
export const MAX_HDR_HEADER = 1 << 16;

function checkSize(name, width, height) {
  if (!(Number.isInteger(width) && Number.isInteger(height) && width >= 1 && height >= 1
        && width <= MAX_ENV_SIDE && height <= MAX_ENV_SIDE && width * height <= MAX_ENV_PIXELS)) {
    throw new Error(`${name}: ${width}x${height} pixels; an environment image may have 1..${MAX_ENV_SIDE} `
      + `pixels a side and at most ${MAX_ENV_PIXELS} in all`);
  }
}

/** Bytes as a Latin-1 string (no spread: headers may be 64 KiB). */
function latin1(b) {
  let s = '';
  for (let i = 0; i < b.length; i += 4096) s += String.fromCharCode.apply(null, b.subarray(i, i + 4096));
  return s;
}

/** Python's bytes.strip(): ASCII whitespace only. */
function asciiStrip(s) {
  return s.replace(/^[ \t\n\r\x0b\x0c]+|[ \t\n\r\x0b\x0c]+$/g, '');
}

function sniffLdr(b) {
  if (b[0] === 0x89 && b[1] === 0x50 && b[2] === 0x4e && b[3] === 0x47) return 'PNG';
  if (b[0] === 0xff && b[1] === 0xd8) return 'JPEG';
  if ((b[0] === 0x49 && b[1] === 0x49) || (b[0] === 0x4d && b[1] === 0x4d)) return 'TIFF';
  if (b[0] === 0x42 && b[1] === 0x4d) return 'BMP';
  return null;
}

// --- OpenEXR ------------------------------------------------------------------------------

/** Bytes three's EXRLoader reads for an attribute of each fixed-size type,
 * whatever the size the file declares for it. */
const EXR_FIXED = {
  chromaticities: 32, compression: 1, box2i: 16, envmap: 1, tiledesc: 9, lineOrder: 1, float: 4, v2f: 8,
  v3f: 12, int: 4, rational: 8, timecode: 8,
};

/** A chlist attribute at b[pos .. pos + size) as three's parseChlist walks it:
 * entries (a name and 16 bytes) up to its last byte, a zero. */
function checkChlist(name, b, pos, size) {
  const end = pos + size - 1;
  let p = pos;
  while (p < end) {
    let z = p;
    while (z < end && b[z] !== 0) z++;
    if (z >= end) throw new Error(`${name}: unreadable EXR header (a channel name runs past its list)`);
    p = z + 1 + 16;
  }
  if (p !== end || b[end] !== 0) throw new Error(`${name}: unreadable EXR header (the channel list's entries overrun it)`);
}

/** The dataWindow of an EXR header, read with bounds checks (before any decoding).
 * Each attribute is walked as three's EXRLoader walks it, and refused where the
 * two would part: a fixed-size type declared at another size, a channel list
 * whose entries overrun it, a multi-part or deep file (three reads more than
 * one header). Where they part, three's header reader can run past the end of
 * the file looking for a string's end and never return (the page fuzz found 119
 * such files in 500,000). */
function exrDataWindow(name, b) {
  const dv = new DataView(b.buffer, b.byteOffset, b.byteLength);
  if (b.length < 8) throw new Error(`${name}: unreadable EXR header (truncated)`);
  if (b[5] & (8 | 16)) {
    throw new Error(`${name}: a multi-part or deep EXR; save the environment as a single-part scanline EXR`);
  }
  let pos = 8;
  const cstr = () => {
    const start = pos;
    while (pos < b.length && b[pos] !== 0 && pos - start < 256) pos++;
    if (pos >= b.length || b[pos] !== 0) throw new Error(`${name}: unreadable EXR header (truncated or corrupt)`);
    const s = latin1(b.subarray(start, pos));
    pos++;
    return s;
  };
  let win = null;
  for (let attrs = 0; attrs < 4096; attrs++) {
    const attr = cstr();
    if (attr === '') break;
    const type = cstr();
    if (pos + 4 > b.length) throw new Error(`${name}: unreadable EXR header (truncated)`);
    const size = dv.getInt32(pos, true);
    pos += 4;
    if (size < 0 || pos + size > b.length) throw new Error(`${name}: unreadable EXR header (attribute ${attr} size ${size})`);
    if (Object.prototype.hasOwnProperty.call(EXR_FIXED, type) && size !== EXR_FIXED[type]) {
      throw new Error(`${name}: unreadable EXR header (attribute ${attr}: a ${type} of ${size} bytes, not ${EXR_FIXED[type]})`);
    }
    if (type === 'chlist') checkChlist(name, b, pos, size);
    if (attr === 'dataWindow' && !win) {
      if (type !== 'box2i' || size !== 16) throw new Error(`${name}: unreadable EXR header (dataWindow is ${type})`);
      win = [0, 4, 8, 12].map((o) => dv.getInt32(pos + o, true));
    }
    pos += size;
  }
  if (!win) throw new Error(`${name}: unreadable EXR header (no dataWindow)`);
  return { width: win[2] - win[0] + 1, height: win[3] - win[1] + 1 };
}

async function decodeExr(name, b) {
  const { width, height } = exrDataWindow(name, b);
  checkSize(name, width, height);
  const { THREE, EXRLoader } = await exrLoader();
  const loader = new EXRLoader();
  loader.setDataType(THREE.FloatType);
  let r;
  try {
    r = loader.parse(b.buffer.slice(b.byteOffset, b.byteOffset + b.byteLength));
  } catch (e) {
    throw new Error(`${name}: unreadable EXR (${e && e.message ? e.message : e})`);
  }
  if (!r || r.width !== width || r.height !== height) {
    throw new Error(`${name}: unreadable EXR (decoded ${r && r.width}x${r && r.height}, header says ${width}x${height})`);
  }
  const channels = 4;   // EXRLoader's RGBAFormat output (alpha 1 where the file has none)
  if (!(r.data instanceof Float32Array) || r.data.length !== width * height * channels) {
    throw new Error(`${name}: unreadable EXR (decoded ${r.data ? r.data.length : 0} values, `
      + `${width * height * channels} expected)`);
  }
  // EXRLoader writes the file's last row first (flipY = false); back to file order.
  const rowLen = width * channels;
  const data = new Float32Array(r.data.length);
  for (let y = 0; y < height; y++) data.set(r.data.subarray((height - 1 - y) * rowLen, (height - y) * rowLen), y * rowLen);
  return { data, width, height, channels };
}

// --- Radiance RGBE (a port of image_io._read_radiance) ---------------------------------------

function decodeRadiance(name, b) {
  // Header lines up to the empty one, at most MAX_HDR_HEADER bytes.
  let pos = 0;
  let fmt = null;
  const readLine = (limit) => {
    const start = pos;
    const end = Math.min(b.length, start + limit);
    let i = start;
    while (i < end && b[i] !== 0x0a) i++;
    const complete = i < end;
    pos = complete ? i + 1 : end;
    return { text: latin1(b.subarray(start, complete ? i + 1 : end)), complete, used: pos - start };
  };
  let used = 0;
  for (;;) {
    const line = readLine(MAX_HDR_HEADER - used + 1);
    used += line.used;
    if (used > MAX_HDR_HEADER) throw new Error(`${name}: Radiance header longer than ${MAX_HDR_HEADER} bytes (corrupt)`);
    if (!line.complete) throw new Error(`${name}: truncated Radiance header`);
    const t = asciiStrip(line.text);
    if (!t) break;
    if (t.startsWith('FORMAT=')) fmt = t.slice(7);
  }
  if (fmt !== null && fmt !== '32-bit_rle_rgbe') {
    throw new Error(`${name}: unsupported Radiance format ${fmt.slice(0, 40)}`);
  }
  const res = readLine(256).text.match(/^([-+])Y\s+(\d+)\s+([-+])X\s+(\d+)\s*$/);
  if (!res || res[2].length > 18 || res[4].length > 18) throw new Error(`${name}: unsupported Radiance resolution line`);
  if (res[3] !== '+') throw new Error(`${name}: Radiance images stored right-to-left are not supported`);
  const height = Number(res[2]), width = Number(res[4]);
  checkSize(name, width, height);
  const buf = b.subarray(pos, Math.min(b.length, pos + height * (4 + 8 * width)));
  const n = buf.length;
  const rgbe = new Uint8Array(width * height * 4);
  let p = 0;
  for (let row = 0; row < height; row++) {
    const out = row * width * 4;
    if (p + 4 > n) throw new Error(`${name}: truncated Radiance pixel data`);
    const b0 = buf[p], b1 = buf[p + 1], b2 = buf[p + 2], b3 = buf[p + 3];
    if (!(width >= 8 && width < 0x8000 && b0 === 2 && b1 === 2 && !(b2 & 0x80))) {
      // Flat (uncompressed) scanline.
      if (p + 4 * width > n) throw new Error(`${name}: truncated Radiance pixel data`);
      rgbe.set(buf.subarray(p, p + 4 * width), out);
      p += 4 * width;
      continue;
    }
    if (((b2 << 8) | b3) !== width) throw new Error(`${name}: Radiance scanline width mismatch`);
    p += 4;
    for (let c = 0; c < 4; c++) {
      let x = 0;
      while (x < width) {
        if (p >= n) throw new Error(`${name}: truncated Radiance run-length data`);
        let count = buf[p++];
        if (count > 128) {
          count -= 128;
          if (x + count > width || p >= n) throw new Error(`${name}: corrupt Radiance run-length data`);
          const v = buf[p++];
          for (let i = 0; i < count; i++) rgbe[out + 4 * (x + i) + c] = v;
        } else {
          if (count === 0 || x + count > width || p + count > n) {
            throw new Error(`${name}: corrupt Radiance run-length data`);
          }
          for (let i = 0; i < count; i++) rgbe[out + 4 * (x + i) + c] = buf[p + i];
          p += count;
        }
        x += count;
      }
    }
  }
  // (m + 0.5) 2^(e - 136) for e > 0, else 0; "+Y" files are stored bottom row first.
  const data = new Float32Array(width * height * 3);
  const flip = res[1] === '+';
  for (let row = 0; row < height; row++) {
    const src = row * width * 4;
    const dst = (flip ? height - 1 - row : row) * width * 3;
    for (let x = 0; x < width; x++) {
      const e = rgbe[src + 4 * x + 3];
      const scale = e > 0 ? 2 ** (e - 136) : 0.0;
      data[dst + 3 * x] = (rgbe[src + 4 * x] + 0.5) * scale;
      data[dst + 3 * x + 1] = (rgbe[src + 4 * x + 1] + 0.5) * scale;
      data[dst + 3 * x + 2] = (rgbe[src + 4 * x + 2] + 0.5) * scale;
    }
  }
  return { data, width, height, channels: 3 };
}

/**
 * Decode an equirect environment (.exr or Radiance .hdr, told apart by their
 * magic bytes) and project it to SH.
 * @param {Uint8Array|ArrayBuffer} bytes the file's bytes
 * @param {string} name the file's name, for messages
 * @param {number} bands 1..8
 * @returns {Promise<{L: number[][], width: number, height: number, name: string}>} L: K = bands^2
 *   [r, g, b], the unrotated light at strength 1 (envmap.project_equirect).
 *   Undecodable, oversized or non-finite input rejects with an Error naming `name`.
 */
export async function environmentFromBytes(bytes, name, bands) {
  if (!Number.isInteger(bands) || bands < 1 || bands > MAX_PROJECT_BANDS) {
    throw new Error(`bands must be an integer in 1..${MAX_PROJECT_BANDS}, got ${bands}`);
  }
  let b;
  if (bytes instanceof Uint8Array) b = bytes;
  else if (bytes instanceof ArrayBuffer) b = new Uint8Array(bytes);
  else if (ArrayBuffer.isView(bytes)) b = new Uint8Array(bytes.buffer, bytes.byteOffset, bytes.byteLength);
  else throw new Error(`${name}: expected the file's bytes (Uint8Array or ArrayBuffer)`);
  let img;
  if (b.length >= 4 && b[0] === 0x76 && b[1] === 0x2f && b[2] === 0x31 && b[3] === 0x01) {
    img = await decodeExr(name, b);
  } else if (b.length >= 2 && b[0] === 0x23 && b[1] === 0x3f) {
    img = decodeRadiance(name, b);
  } else {
    const kind = sniffLdr(b);
    if (kind) throw new Error(`${name}: a ${kind} image is not HDR; use an OpenEXR (.exr) or Radiance (.hdr) environment`);
    throw new Error(`${name}: not an OpenEXR or Radiance HDR file`);
  }
  let L;
  try {
    L = projectEquirect(img.data, img.width, img.height, img.channels, bands);
  } catch (e) {
    throw new Error(`${name}: ${e.message}`);
  }
  return { L, width: img.width, height: img.height, name };
}

/** Seconds the page gives an environment to decode and project: a damaged
 * file can keep three's EXRLoader in a loop for ever (docs/fuzzing.md), so the
 * worker doing it is ended after this (plus a second per MiB of file). */
export const ENV_DECODE_SECONDS = 30;

/**
 * environmentFromBytes in a Web Worker that is ended when it takes longer
 * than `seconds` + 1 s per MiB: the page stays responsive while a large image
 * decodes, and a file that would never finish is an Error naming it.
 * @param {Uint8Array} bytes the file's bytes (copied to the worker)
 * @param {string} name the file's name, for messages
 * @param {number} bands 1..8
 * @param {number} [seconds] the base limit (ENV_DECODE_SECONDS)
 * @returns {Promise<{L: number[][], width: number, height: number, name: string}>} as environmentFromBytes
 */
export function environmentInWorker(bytes, name, bands, seconds = ENV_DECODE_SECONDS) {
  const limit = seconds + bytes.byteLength / (1 << 20);
  const worker = new Worker(new URL('./prtt_env_worker.js', import.meta.url), { type: 'module' });
  return new Promise((resolve, reject) => {
    const done = (fn, v) => { clearTimeout(timer); worker.terminate(); fn(v); };
    const timer = setTimeout(() => done(reject, new Error(
      `${name}: not decoded after ${limit.toFixed(0)} s (a damaged file?); the page stopped reading it`)), limit * 1000);
    worker.onmessage = ({ data }) => (data.error !== undefined ? done(reject, new Error(data.error)) : done(resolve, data.env));
    worker.onerror = (ev) => { ev.preventDefault(); done(reject, new Error(`${name}: the decoder failed (${ev.message || 'worker error'})`)); };
    const copy = bytes.slice();
    worker.postMessage({
      bytes: copy, name, bands,
      three: import.meta.resolve('three'), exrLoader: import.meta.resolve('three/addons/loaders/EXRLoader.js'),
    }, [copy.buffer]);
  });
}
