// The page's environment decoder off the main thread (prtt_env.js
// environmentInWorker): one message {bytes, name, bands, three, exrLoader} in,
// {env} or {error} out; the page ends the worker when it runs too long.
//
// Import maps do not reach workers (Chromium 156), and three's EXRLoader
// imports the bare specifier 'three' and a relative '../libs/fflate.module.js'.
// So the loader's source is fetched and imported from a blob with each of its
// import specifiers made absolute: `three` is the URL the page's import map
// resolved, a relative one is resolved against the loader's own URL.
import { environmentFromBytes, useExrModules } from './prtt_env.js';

async function modulesFor(threeUrl, loaderUrl) {
  const THREE = await import(threeUrl);
  const r = await fetch(loaderUrl);
  if (!r.ok) throw new Error(`${loaderUrl}: HTTP ${r.status}`);
  const src = await r.text();
  // Import statements only (a line that starts with import or export): the
  // loader's documentation quotes an import too.
  const specifiers = /^((?:import|export)\b[^;]*?\bfrom\s*)(['"])([^'"]+)\2/gm;
  const absolute = src.replace(specifiers, (_, from, q, spec) => {
    if (spec === 'three') return `${from}${q}${threeUrl}${q}`;
    if (spec.startsWith('.')) return `${from}${q}${new URL(spec, loaderUrl).href}${q}`;
    throw new Error(`${loaderUrl}: imports ${spec}, which a worker cannot resolve`);
  });
  const url = URL.createObjectURL(new Blob([absolute], { type: 'text/javascript' }));
  try {
    const { EXRLoader } = await import(url);
    return { THREE, EXRLoader };
  } finally {
    URL.revokeObjectURL(url);
  }
}

self.onmessage = async ({ data }) => {
  const { bytes, name, bands, three, exrLoader } = data;
  try {
    useExrModules(() => modulesFor(three, exrLoader));
    postMessage({ env: await environmentFromBytes(bytes, name, bands) });
  } catch (e) {
    postMessage({ error: String(e && e.message ? e.message : e) });
  }
};
