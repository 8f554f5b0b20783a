"""The page's own readers, fuzzed in node (the JavaScript the browser runs):
viewer/prtt_env.js ``environmentFromBytes`` (a dropped .exr or .hdr) and
viewer/prtt_textures.js ``arrayTexture`` (a KTX2 payload against what the glTF
extension says it holds).

There is no coverage feedback across the language boundary: the inputs are
mutants of the seeds (the same real .exr, .hdr and KTX2 files the Python
harnesses start from) made by :func:`mutate`, deterministic in ``seed``:
bit flips, interesting integers over 1, 2 and 4 bytes, inserted, erased and
duplicated runs, splices of two seeds, truncation. page_fuzz.mjs runs a
bundle of them in one node process and reports what was answered outside the
contract (anything but an Error naming the input), inputs over 1 s and its
peak RSS.
"""
from __future__ import annotations

import json
import os
import random
import shutil
import struct
import subprocess
import tempfile
import time

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))
NODE_MODULES_PARENT = os.path.join(ROOT, "tools", "js", "package.json")
INTERESTING = [0, 1, 0x7F, 0x80, 0xFF, 0x100, 0x7FFF, 0x8000, 0xFFFF, 0x10000, 0x7FFFFFFF, 0x80000000, 0xFFFFFFFF]
#: Inputs per node process (a bundle), and the seconds it may take (a few, normally).
BUNDLE = 2000
BUNDLE_SECONDS = 90

_HOOKS = """
let parent;
export async function initialize(data) { parent = data.parent; }
export async function resolve(specifier, context, next) {
  if (!/^(\\.|\\/|node:|file:|data:)/.test(specifier)) return next(specifier, { ...context, parentURL: parent });
  return next(specifier, context);
}
"""


def mutate(data: bytes, rng: random.Random, others: list[bytes], max_len: int = 1 << 16) -> bytes:
    """One mutant of ``data``: 1 to 4 stacked mutations."""
    b = bytearray(data)
    for _ in range(rng.randint(1, 4)):
        op = rng.randrange(7)
        n = len(b)
        if op == 0 and n:                                   # flip bits
            for _ in range(rng.randint(1, 8)):
                b[rng.randrange(n)] ^= 1 << rng.randrange(8)
        elif op == 1 and n >= 4:                            # an interesting integer
            w = rng.choice((1, 2, 4))
            at = rng.randrange(n - w + 1)
            v = rng.choice(INTERESTING) + rng.choice((0, 0, -1, 1))
            b[at:at + w] = (v % (1 << (8 * w))).to_bytes(w, rng.choice(("little", "big")))
        elif op == 2:                                       # insert random or repeated bytes
            at = rng.randrange(n + 1)
            k = rng.randint(1, 64)
            ins = bytes([rng.randrange(256)]) * k if rng.random() < 0.5 else rng.randbytes(k)
            b[at:at] = ins
        elif op == 3 and n > 1:                             # erase a run
            at = rng.randrange(n)
            del b[at:at + rng.randint(1, max(1, n // 8))]
        elif op == 4 and n > 1:                             # duplicate a run elsewhere
            at, k = rng.randrange(n), rng.randint(1, 256)
            b[rng.randrange(n):rng.randrange(n)] = b[at:at + k]
        elif op == 5 and others:                            # splice with another seed
            o = rng.choice(others)
            cut = rng.randrange(len(b) + 1)
            b = b[:cut] + o[rng.randrange(len(o) + 1):]
        elif op == 6 and n > 1:                             # truncate
            b = b[:rng.randrange(n)]
    return bytes(b[:max_len])


def _bundle(path: str, items: list[tuple[str, bytes, dict | None]]) -> None:
    head = json.dumps({"items": [[k, len(d), spec] for k, d, spec in items]}).encode()
    with open(path, "wb") as f:
        f.write(struct.pack("<II", len(head), 0) + head)
        for _, d, _ in items:
            f.write(d)


def _keep(found_dir: str | None, name: str, data: bytes) -> None:
    """Save an input the page's readers answered outside their contract (or hung on)."""
    if found_dir:
        os.makedirs(found_dir, exist_ok=True)
        with open(os.path.join(found_dir, name), "wb") as f:
            f.write(data)


def run_bundle(items: list[tuple[str, bytes, dict | None]], bundle: str,
               viewer: str = os.path.join(ROOT, "viewer")) -> tuple[dict | None, str]:
    """Run ``items`` (kind "env" or "ktx2", bytes, the KTX2's spec) through
    page_fuzz.mjs in one node process, the bundle written to ``bundle``;
    returns (its report, or None, and why not)."""
    node = shutil.which("node")
    if node is None:
        raise RuntimeError("node is not installed: the page's readers cannot run (tools/bootstrap.sh)")
    _bundle(bundle, items)
    here = os.path.dirname(bundle)
    with open(os.path.join(here, "hooks.mjs"), "w") as f:
        f.write(_HOOKS)
    with open(os.path.join(here, "register.mjs"), "w") as f:
        f.write("import { register } from 'node:module';\n"
                f"register(new URL('./hooks.mjs', import.meta.url), "
                f"{{ data: {{ parent: {json.dumps('file://' + NODE_MODULES_PARENT)} }} }});\n")
    try:
        # A bundle runs in a few seconds: one that takes BUNDLE_SECONDS holds an input that crashed
        # or stalled node itself (an input that hangs a decoder is timed in page_fuzz.mjs).
        p = subprocess.run([node, "--import", "file://" + os.path.join(here, "register.mjs"),
                            os.path.join(os.path.dirname(__file__), "page_fuzz.mjs"), bundle,
                            viewer], capture_output=True, text=True, timeout=BUNDLE_SECONDS)
    except subprocess.TimeoutExpired:
        return None, f"node did not finish {len(items)} inputs in {BUNDLE_SECONDS} s"
    if p.returncode != 0:
        return None, f"node exited with {p.returncode}: {p.stderr.strip()[-300:]}"
    return json.loads(p.stdout.strip().splitlines()[-1]), ""


def run(seeds: dict, runs: int, *, seed: int = 1, found_dir: str | None = None,
        viewer: str = os.path.join(ROOT, "viewer")) -> dict:
    """Fuzz the page's readers (the modules in ``viewer``) with ``runs``
    mutants (half environments, half KTX2 payloads); returns the report
    __main__ prints."""
    node = shutil.which("node")
    if node is None:
        raise RuntimeError("node is not installed: the page's readers cannot run (tools/bootstrap.sh)")
    def read(path: str) -> bytes:
        with open(path, "rb") as f:
            return f.read()
    env_seeds = [read(p) for p in seeds["env"]]
    specs = os.path.dirname(seeds["ktx2-specs"][0])
    ktx = [(read(p), json.loads(read(os.path.join(specs, os.path.basename(p) + ".json")))) for p in seeds["ktx2"]]
    rng = random.Random(seed)
    t0 = time.perf_counter()
    done, failures, hangs, slowest, rss, accepted = 0, [], [], 0.0, 0, 0
    with tempfile.TemporaryDirectory(prefix="prtt-page-fuzz-") as tmp:
        while done < runs:
            items = []
            for _ in range(min(BUNDLE, runs - done)):
                if rng.random() < 0.5:
                    items.append(("env", mutate(rng.choice(env_seeds), rng, env_seeds), None))
                else:
                    blob, spec = rng.choice(ktx)
                    items.append(("ktx2", mutate(blob, rng, [b for b, _ in ktx]), spec))
            bundle = os.path.join(tmp, "bundle.bin")
            r, why = run_bundle(items, bundle, viewer)
            if r is None:
                # Keep the whole bundle: one of its inputs hung or crashed the reader.
                name = f"page-bundle-{len(failures):03d}"
                if found_dir:
                    os.makedirs(found_dir, exist_ok=True)
                    shutil.copy(bundle, os.path.join(found_dir, name))
                failures.append(f"{name}: {why}")
                done += len(items)
                continue
            for i, why in r["failures"]:
                name = f"page-{items[i][0]}-{len(failures):03d}"
                _keep(found_dir, name, items[i][1])
                failures.append(f"{name}: {why}")
            for i in r["hangs"]:
                name = f"page-hang-{len(hangs):03d}"
                _keep(found_dir, name, items[i][1])
                hangs.append(name)
            slowest = max(slowest, r["slowest_ms"])
            rss = max(rss, r["maxrss_kb"] // 1024)
            done += r["executions"]
            accepted += r["accepted"]
    wall = time.perf_counter() - t0
    return {"target": "page", "reader": "viewer: environmentFromBytes, arrayTexture (node, mutational)",
            "executions": done, "seconds": round(wall, 1), "exec_per_s": int(done / max(wall, 1e-9)),
            "peak_rss_mb": rss, "corpus": len(env_seeds) + len(ktx), "findings": failures, "exit": 0,
            "slowest_ms": round(slowest, 1), "accepted": accepted, "hangs": hangs}
