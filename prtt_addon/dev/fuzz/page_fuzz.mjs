// The page's own readers on a bundle of inputs (prtt_addon/dev/fuzz/page.py writes
// it): viewer/prtt_env.js environmentFromBytes (a dropped .exr or .hdr) and
// viewer/prtt_textures.js arrayTexture (a KTX2 payload, checked against what the
// extension says it holds). Prints one JSON line: executions, the inputs
// answered outside the contract (an Error naming the input, or a result),
// the slowest input and the process's peak RSS.
//
//   node --import <register.mjs> page_fuzz.mjs BUNDLE VIEWER_DIR
import fs from 'node:fs';
import { pathToFileURL } from 'node:url';

const [bundlePath, viewerDir] = process.argv.slice(2);
const { environmentFromBytes } = await import(pathToFileURL(`${viewerDir}/prtt_env.js`).href);
const { arrayTexture } = await import(pathToFileURL(`${viewerDir}/prtt_textures.js`).href);
const { ZSTDDecoder } = await import('three/addons/libs/zstddec.module.js');
const zstd = new ZSTDDecoder();
await zstd.init();

const bundle = fs.readFileSync(bundlePath);
const head = JSON.parse(bundle.subarray(8, 8 + bundle.readUInt32LE(0)).toString('utf8'));
let pos = 8 + bundle.readUInt32LE(0);
const failures = [];
let slowest = [0, -1];
let accepted = 0;
for (let i = 0; i < head.items.length; i++) {
  const [kind, len, spec] = head.items[i];
  const bytes = new Uint8Array(bundle.buffer, bundle.byteOffset + pos, len).slice();
  pos += len;
  const name = `input${i}.${kind}`;
  const t0 = performance.now();
  try {
    if (kind === 'env') await environmentFromBytes(bytes, name, 3);
    else arrayTexture(bytes, zstd, name, spec, null);
    accepted += 1;
  } catch (e) {
    if (!(e instanceof Error) || !String(e.message).includes(name)) {
      failures.push([i, `${e && e.constructor ? e.constructor.name : typeof e}: ${e && e.message}`]);
    }
  }
  const ms = performance.now() - t0;
  if (ms > slowest[0]) slowest = [ms, i];
  if (ms > 1000) failures.push([i, `took ${ms.toFixed(0)} ms`]);
}
process.stdout.write(JSON.stringify({ executions: head.items.length, accepted, failures, slowest_ms: slowest[0],
  slowest: slowest[1], maxrss_kb: process.resourceUsage().maxRSS }) + '\n');
