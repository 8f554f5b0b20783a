// The page's own readers on a bundle of inputs (prtt_addon/dev/fuzz/page.py writes
// it): viewer/prtt_env.js environmentFromBytes (a dropped .exr or .hdr) and
// viewer/prtt_textures.js arrayTexture (a KTX2 payload, checked against what the
// extension says it holds). Prints one JSON line: executions, the inputs
// answered outside the contract (an Error naming the input, or a result),
// the slowest input, the inputs that hung (contained as the page contains
// them) and the process's peak RSS.
//
//   node --import <register.mjs> page_fuzz.mjs BUNDLE VIEWER_DIR
import fs from 'node:fs';
import { pathToFileURL } from 'node:url';
import { Worker } from 'node:worker_threads';

const [bundlePath, viewerDir] = process.argv.slice(2);
const { arrayTexture } = await import(pathToFileURL(`${viewerDir}/prtt_textures.js`).href);
const { ZSTDDecoder } = await import('three/addons/libs/zstddec.module.js');
const zstd = new ZSTDDecoder();
await zstd.init();

// Environments decode in a worker thread, as the page decodes them in a Web
// Worker it ends after a time limit (prtt_env.js environmentInWorker): an
// input with no answer in HANG_MS ends the worker and is reported as a hang,
// which the page turns into a message; the bundle goes on with a new worker.
const HANG_MS = 5000;
const ENV_WORKER = `
  const { parentPort } = require('node:worker_threads');
  import(${JSON.stringify(pathToFileURL(`${viewerDir}/prtt_env.js`).href)}).then(({ environmentFromBytes, useExrModules }) => {
    // The main thread's resolve hook (the page's import map) does not reach a worker: three by URL.
    useExrModules(async () => ({ THREE: await import(${JSON.stringify(import.meta.resolve('three'))}),
      EXRLoader: (await import(${JSON.stringify(import.meta.resolve('three/addons/loaders/EXRLoader.js'))})).EXRLoader }));
    parentPort.on('message', async ({ bytes, name }) => {
      try {
        await environmentFromBytes(bytes, name, 3);
        parentPort.postMessage({ ok: true });
      } catch (e) {
        parentPort.postMessage({ ok: false, isError: e instanceof Error,
          type: e && e.constructor ? e.constructor.name : typeof e, message: String(e && e.message) });
      }
    });
    parentPort.postMessage({ ready: true });
  });`;
let envWorker = null;
async function startWorker() {
  envWorker = new Worker(ENV_WORKER, { eval: true });
  await new Promise((resolve, reject) => {
    envWorker.once('message', () => { envWorker.removeAllListeners('error'); resolve(); });
    envWorker.once('error', reject);
  });
}
function decodeEnv(bytes, name) {
  // An answer, a hang (no answer in HANG_MS: the worker is ended), or the worker's death
  // (an exception outside the reader, out of memory): a crash, reported as a finding.
  return new Promise((resolve) => {
    const w = envWorker;
    const done = (r) => {
      clearTimeout(timer);
      w.removeAllListeners('message');
      w.removeAllListeners('error');
      w.removeAllListeners('exit');
      resolve(r);
    };
    const timer = setTimeout(() => { w.terminate(); envWorker = null; done({ hang: true }); }, HANG_MS);
    w.once('message', (r) => done(r));
    w.once('error', (e) => { envWorker = null; done({ ok: false, isError: false, type: 'crash', message: String(e) }); });
    w.once('exit', (code) => { envWorker = null; done({ ok: false, isError: false, type: 'crash', message: `the decoder's worker exited (${code})` }); });
    w.postMessage({ bytes, name }, [bytes.buffer]);
  });
}

const bundle = fs.readFileSync(bundlePath);
const head = JSON.parse(bundle.subarray(8, 8 + bundle.readUInt32LE(0)).toString('utf8'));
let pos = 8 + bundle.readUInt32LE(0);
const failures = [];
const hangs = [];
let slowest = [0, -1];
let accepted = 0;
for (let i = 0; i < head.items.length; i++) {
  const [kind, len, spec] = head.items[i];
  const bytes = new Uint8Array(bundle.buffer, bundle.byteOffset + pos, len).slice();
  pos += len;
  const name = `input${i}.${kind}`;
  if (kind === 'env' && !envWorker) await startWorker();      // not timed: three is imported again
  const t0 = performance.now();
  if (kind === 'env') {
    const r = await decodeEnv(bytes, name);
    if (r.hang) {
      hangs.push(i);
      continue;
    }
    if (r.ok) accepted += 1;
    else if (!r.isError || !r.message.includes(name)) failures.push([i, `${r.type}: ${r.message}`]);
  } else {
    try {
      arrayTexture(bytes, zstd, name, spec, null);
      accepted += 1;
    } catch (e) {
      if (!(e instanceof Error) || !String(e.message).includes(name)) {
        failures.push([i, `${e && e.constructor ? e.constructor.name : typeof e}: ${e && e.message}`]);
      }
    }
  }
  const ms = performance.now() - t0;
  if (ms > slowest[0]) slowest = [ms, i];
  if (ms > 1000) failures.push([i, `took ${ms.toFixed(0)} ms`]);
}
if (envWorker) await envWorker.terminate();
process.stdout.write(JSON.stringify({ executions: head.items.length, accepted, failures, hangs, slowest_ms: slowest[0],
  slowest: slowest[1], maxrss_kb: process.resourceUsage().maxRSS }) + '\n');
