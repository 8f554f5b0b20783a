"""Try the installed extension in every Blender it claims: ``./prtt.sh compat``.

    ./prtt.sh compat [VERSION ...] [--json FILE] [--work DIR] [--no-page] [--bench]

For each Blender version (default: the oldest claimed, 4.2 LTS; the LTS
lines 4.5 and 5.2; the newest on PyPI, 5.3; ``all`` adds 5.0 and 5.1):

1. a virtual environment with that Blender as a Python module, ``bpy`` from
   PyPI, on the Python that Blender embeds (3.11 for 4.2-5.0, 3.13 for 5.1+)
   and the numpy it ships, made once and kept in ``$PRTT_COMPAT_CACHE``
   (default ``~/.cache/prtt-compat``): nothing else, in particular no numba
   (the zip brings its own) and none of the source tree;
2. this platform's extension zip, built once by tools/build_extension.py;
3. tools/compat_chain.py in that Python: install and enable the zip with
   ``package_install_files`` into an empty user folder, then Unwrap, Bake
   Transfer (the add-on's defaults), the viewport draw handler's draw,
   Render Preview Image in every mode, Export glTF;
4. the exported .glb opened by the web viewer (viewer/) in headless Chromium.

Prints one line per version and a last line saying whether the baked
textures are byte-identical across the versions; exits 1 when a version
fails. ``--json`` writes every result (steps, seconds, hashes).
"""
from __future__ import annotations

import argparse
import concurrent.futures
import hashlib
import json
import os
import shutil
import subprocess
import sys
import tempfile

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
if ROOT not in sys.path:
    sys.path.insert(0, ROOT)              # prtt_addon.dev.bench's page server, when run as a file
# The page benchmark's browser and server over viewer/, shaders/ and tools/js.
from prtt_addon.dev.bench.web_bench import BROWSER, BROWSER_ARGS, Site, page_url  # noqa: E402

CHAIN = os.path.join(ROOT, "tools", "compat_chain.py")
#: Blender line -> the release tried (the newest on PyPI when this was written).
RELEASES = {"4.2": "4.2.23", "4.5": "4.5.15", "5.0": "5.0.1", "5.1": "5.1.2", "5.2": "5.2.3", "5.3": "5.3.0"}
#: What CI tries: the manifest's minimum, the LTS lines, the newest.
DEFAULT = ("4.2", "4.5", "5.2", "5.3")
#: numpy as Blender bundles it: 1.26.4 up to 5.0 (bpy 4.2's own requirement is
#: unpinned and would take numpy 2); 5.1+ let bpy's requirement (>=2.2) choose.
NUMPY = {"4.2": "1.26.4", "4.5": "1.26.4", "5.0": "1.26.4"}


def release(version: str) -> str:
    """'4.5' -> '4.5.15'; a full version is kept as given."""
    return RELEASES.get(version, version)


def line(version: str) -> str:
    return ".".join(version.split(".")[:2])


def python_for(version: str) -> str:
    """The interpreter Blender ``version`` embeds: 3.11 before 5.1, 3.13 from 5.1."""
    major, minor = (int(v) for v in version.split(".")[:2])
    want = "3.13" if (major, minor) >= (5, 1) else "3.11"
    env = os.environ.get("PRTT_PYTHON" + want.replace(".", ""))
    cands = [env] if env else []
    cands.append(shutil.which(f"python{want}"))
    pyenv = os.environ.get("PYENV_ROOT", os.path.expanduser("~/.pyenv"))
    cands += sorted((os.path.join(pyenv, "versions", d, "bin", f"python{want}")
                     for d in (os.listdir(os.path.join(pyenv, "versions"))
                               if os.path.isdir(os.path.join(pyenv, "versions")) else [])
                     if d.startswith(want + ".")), reverse=True)
    for c in cands:
        # a pyenv shim exists but fails when its version is not the active one: ask each
        if c and os.path.exists(c) and subprocess.run(
                [c, "-c", f"import sys; sys.exit(sys.version_info[:2] != {tuple(map(int, want.split('.')))})"],
                capture_output=True).returncode == 0:
            return c
    raise SystemExit(f"Blender {version} needs Python {want}: none found "
                     f"(set PRTT_PYTHON{want.replace('.', '')}=/path/to/python{want})")


def cache_dir() -> str:
    return os.environ.get("PRTT_COMPAT_CACHE") or os.path.expanduser("~/.cache/prtt-compat")


def venv(version: str, log) -> str:
    """The Python of the kept virtual environment for Blender ``version``
    (made when missing or when what it should hold changed)."""
    folder = os.path.join(cache_dir(), f"bpy-{version}")
    py = os.path.join(folder, "bin", "python")
    pins = [f"bpy=={version}"] + ([f"numpy=={NUMPY[line(version)]}"] if line(version) in NUMPY else [])
    stamp = os.path.join(folder, ".prtt-compat")
    if os.path.exists(py) and os.path.exists(stamp):
        with open(stamp, encoding="utf-8") as f:
            if f.read() == " ".join(pins):
                return py
    log(f"[compat] making {folder}: {' '.join(pins)} (bpy is ~370 MB to download, once)")
    shutil.rmtree(folder, ignore_errors=True)
    subprocess.run([python_for(version), "-m", "venv", folder], check=True)
    r = subprocess.run([py, "-m", "pip", "install", "-q", "--disable-pip-version-check", *pins],
                       capture_output=True, text=True)
    if r.returncode:
        raise RuntimeError(f"pip install {' '.join(pins)} failed: {r.stderr.strip().splitlines()[-1:]}")
    with open(stamp, "w", encoding="utf-8") as f:
        f.write(" ".join(pins))
    return py


def build_zip(work: str) -> str:
    """This platform's extension zip, built offline from the wheels cache."""
    sys.path.insert(0, os.path.join(ROOT, "tools"))
    import build_extension
    plat = build_extension.host_platform()
    r = subprocess.run([sys.executable, os.path.join(ROOT, "tools", "build_extension.py"), "--offline",
                        "--platform", plat, "--out", os.path.join(work, "dist"),
                        "--stage", os.path.join(work, "stage")], capture_output=True, text=True)
    if r.returncode:
        raise SystemExit(f"building the extension zip failed:\n{r.stdout}{r.stderr}")
    (name,) = [n for n in os.listdir(os.path.join(work, "dist")) if n.endswith(".zip")]
    return os.path.join(work, "dist", name)


def run_chain(py: str, zip_path: str, work: str, timeout: float) -> dict:
    """tools/compat_chain.py in Blender's Python: its COMPAT record, or a record of why there is none."""
    shutil.rmtree(work, ignore_errors=True)          # a fresh scene, textures and user folder
    os.makedirs(work)
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME")}
    env["BLENDER_USER_RESOURCES"] = os.path.join(work, "blender-user")
    try:
        r = subprocess.run([py, CHAIN, zip_path, work], capture_output=True, text=True, env=env,
                           cwd=work, timeout=timeout)
        out, err, rc = r.stdout, r.stderr, r.returncode
    except subprocess.TimeoutExpired as exc:
        out, err, rc = exc.stdout or "", exc.stderr or "", f"timeout {timeout:.0f} s"
        out, err = (s.decode() if isinstance(s, bytes) else s for s in (out, err))
    with open(os.path.join(work, "chain.log"), "w", encoding="utf-8") as f:
        f.write(out + "\n--- stderr ---\n" + err)
    rec = next((json.loads(ln[7:]) for ln in reversed(out.splitlines()) if ln.startswith("COMPAT ")), None)
    if rec is None:
        tail = [ln for ln in (err or out).splitlines() if ln.strip()][-1:] or [f"exit {rc}"]
        rec = {"steps": {"chain": f"no result (exit {rc}): {tail[0][:200]}"}, "seconds": {}, "files": {}}
    rec["log"] = os.path.join(work, "chain.log")
    return rec


def open_page(site, glb: str, name: str) -> str:
    """'ok (title)' when the web viewer draws ``glb``: its title says ready
    and the canvas is not empty; else what went wrong. ``site``: bench's
    web_bench.Site, the server the page benchmark uses."""
    from playwright.sync_api import sync_playwright
    size = (160, 90)
    src = site.add(glb, name)
    with sync_playwright() as p:
        b = p.chromium.launch(executable_path=BROWSER, args=BROWSER_ARGS)
        try:
            page = b.new_page(viewport={"width": size[0], "height": size[1]})
            errors = []
            page.on("pageerror", lambda e: errors.append(str(e)))
            page.goto(page_url(site, src, size))
            page.wait_for_function("document.title.startsWith('ready') || document.title.startsWith('error')",
                                   timeout=120_000)
            title = page.title()
            if not title.startswith("ready"):
                return title
            lit = page.evaluate("""() => { const c = document.querySelector('canvas');
                const g = document.createElement('canvas'); g.width = c.width; g.height = c.height;
                const x = g.getContext('2d'); x.drawImage(c, 0, 0);
                const d = x.getImageData(0, 0, c.width, c.height).data; let n = 0;
                for (let i = 0; i < d.length; i += 4) n += (d[i] + d[i + 1] + d[i + 2]) > 0;
                return n / (c.width * c.height); }""")
            if errors:
                return f"page error: {errors[0][:200]}"
            if lit < 0.05:
                return f"{title}, but only {100 * lit:.0f} % of the canvas drawn"
            return f"ok ({title}, {100 * lit:.0f} % drawn)"
        finally:
            b.close()


def _decoded(path: str) -> dict:
    import OpenEXR
    with OpenEXR.File(path) as f:
        return {k: c.pixels.copy() for k, c in f.channels().items()}


def _step_ulps(path: str) -> int:
    """Ulps of the file's storage in one step of its precision: 2^(10 - m)
    half ulps where the bake kept m of half's 10 mantissa bits (tuning auto,
    the header's prtt_mantissa_bits), else 1."""
    import OpenEXR
    with OpenEXR.File(path) as f:
        bits = f.header().get("prtt_mantissa_bits")
    return 1 << (10 - int(bits)) if bits is not None else 1


def _ordered(a: np.ndarray) -> np.ndarray:
    """A float array's bit patterns as int64 in the order of their values, so
    that the difference of two is their distance in steps of the stored
    precision (ulps; +0 and -0 the same)."""
    bits = a.view(f"i{a.itemsize}").astype(np.int64)
    magnitude = bits & ((1 << (8 * a.itemsize - 1)) - 1)
    return np.where(bits < 0, -magnitude, magnitude)


def compare_textures(results: dict, work: str) -> dict | None:
    """The second bake's textures (xatlas UVs: the same in every Blender)
    compared across the versions that made them: by their bytes, and where
    those differ, by their decoded values (``max_abs_difference`` 0 when
    every value is the same number: the only difference is the sign of some
    zeros; ``largest_value``: the file's largest magnitude, to judge the rest;
    ``max_steps``: the largest difference in steps of the precision the file
    keeps (half or float ulps, or the mantissa bits tuning auto keeps), and
    ``values``: how many values the file holds)."""
    hashed = {v: {k: h for k, h in r.get("files", {}).items() if h} for v, r in results.items() if r.get("files")}
    if len(hashed) < 2:
        return None
    first = next(iter(hashed))
    names = sorted(set().union(*hashed.values()))
    out = {"reference": first, "files": {}}
    for name in names:
        for v in hashed:
            if v == first or hashed[v].get(name) == hashed[first].get(name):
                continue
            a = _decoded(os.path.join(work, first, "textures", name))
            b = _decoded(os.path.join(work, v, "textures", name))
            if a.keys() != b.keys():
                out["files"].setdefault(name, {})[v] = "different channels"
                continue
            bits = sum(int((a[k].view(f"u{a[k].itemsize}") != b[k].view(f"u{b[k].itemsize}")).sum()) for k in a)
            worst = max(float(np.nanmax(np.abs(a[k].astype(np.float64) - b[k].astype(np.float64)), initial=0.0))
                        for k in a)
            largest = max(float(np.nanmax(np.abs(a[k].astype(np.float64)), initial=0.0)) for k in a)
            ulps = max(int(np.abs(_ordered(a[k]) - _ordered(b[k])).max(initial=0)) for k in a)
            steps = ulps / _step_ulps(os.path.join(work, first, "textures", name))
            out["files"].setdefault(name, {})[v] = {"values_differing_in_bits": bits, "max_abs_difference": worst,
                                                    "largest_value": largest, "max_steps": steps,
                                                    "values": sum(int(a[k].size) for k in a)}
    if not out["files"]:
        out["summary"] = f"{len(names)} files, byte-identical across {', '.join(hashed)}"
    else:
        parts = []
        for name, per in out["files"].items():
            for v, d in per.items():
                parts.append(f"{name} {first} vs {v}: " + (d if isinstance(d, str) else
                             (f"{d['values_differing_in_bits']} values differ only in the sign of zero"
                              if d["max_abs_difference"] == 0 else
                              f"{d['values_differing_in_bits']} values differ, at most {d['max_abs_difference']:.3g} "
                              f"({d['max_steps']:g} steps of its precision)")))
        same = [n for n in names if n not in out["files"]]
        out["summary"] = (f"{len(names)} files; byte-identical: {', '.join(same) or 'none'}; " + "; ".join(parts))
    return out


BENCH = os.path.join(ROOT, "tools", "compat_bench.py")


def bench_one(py: str, zip_path: str | None, work: str, timeout: float) -> dict:
    """tools/compat_bench.py's two steps in one Python (``zip_path`` None: the
    source tree): its BENCH record, or {"error": ...}."""
    shutil.rmtree(work, ignore_errors=True)
    os.makedirs(work)
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME")}
    env["BLENDER_USER_RESOURCES"] = os.path.join(work, "blender-user")
    blend = os.path.join(work, "demo.blend")
    runs = [([py, BENCH, "scene", blend], dict(env, PYTHONPATH=ROOT)),
            ([py, BENCH, "bake", blend, work] + ([zip_path] if zip_path else []),
             env if zip_path else dict(env, PYTHONPATH=ROOT))]
    out = ""
    for cmd, e in runs:
        r = subprocess.run(cmd, capture_output=True, text=True, env=e, cwd=work, timeout=timeout)
        out = r.stdout
        if r.returncode:
            tail = [ln for ln in (r.stderr or r.stdout).splitlines() if ln.strip()][-1:] or [f"exit {r.returncode}"]
            return {"error": f"{os.path.basename(cmd[2])} {cmd[2]} step: {tail[0][:200]}"}
    return next((json.loads(ln[6:]) for ln in reversed(out.splitlines()) if ln.startswith("BENCH ")),
                {"error": "no BENCH record"})


def bench(versions, pythons, zip_path: str, work: str, timeout: float) -> dict:
    """The demo's default bake in the development venv (before and after the
    Blenders, the faster counts) and through the zip in each Blender: {name: record}."""
    out = {"development": bench_one(sys.executable, None, os.path.join(work, "bench-dev"), timeout)}
    print(bench_line("development", out["development"], None), flush=True)
    for v in versions:
        out[v] = bench_one(pythons[v], zip_path, os.path.join(work, f"bench-{v}"), timeout)
        print(bench_line(v, out[v], out["development"]), flush=True)
    again = bench_one(sys.executable, None, os.path.join(work, "bench-dev"), timeout)
    if fastest(again) < fastest(out["development"]):
        out["development"] = again
    print(bench_line("development", again, None) + "  (again)", flush=True)
    return out


def fastest(rec: dict, key: str = "seconds") -> float:
    """The fastest timed bake of a record (the first round warms numba's
    cache): as the user waits for it (``seconds``) or in the worker (``worker_seconds``)."""
    return min((b[key] for b in rec.get("bakes", [])[1:]), default=float("inf"))


def bench_line(name: str, rec: dict, dev: dict | None) -> str:
    if "error" in rec:
        return f"bench {name:<12} FAIL {rec['error']}"
    shading = sorted({s for b in rec["bakes"] for s in b["hit_shading"]})
    times = ", ".join(f"{b['seconds']:.1f}" for b in rec["bakes"])
    ratio = (f"  {fastest(rec) / fastest(dev):.3f} / {fastest(rec, 'worker_seconds') / fastest(dev, 'worker_seconds'):.3f}"
             " x development" if dev and "error" not in dev else "")
    return (f"bench {name:<12} Blender {rec['blender']:<8} numba {rec['numba'] or 'none':<7} "
            f"shading {'/'.join(shading)}  demo bake {fastest(rec):.2f} s, worker {fastest(rec, 'worker_seconds'):.2f} s "
            f"(rounds {times}){ratio}")


def summary(version: str, rec: dict) -> str:
    steps, secs = rec["steps"], rec["seconds"]
    bad = {k: v for k, v in steps.items() if not (v == "ok" or v.startswith("ok "))}
    head = f"Blender {rec.get('blender', version):<14} py {rec.get('python', '?'):<7} numpy {rec.get('numpy', '?'):<7}"
    if bad:
        step, why = next(iter(bad.items()))
        return f"{head} FAIL at {step}: {why}"
    shading = "/".join(rec.get("hit_shading") or ["?"])
    return (f"{head} PASS  install {secs.get('install', 0):.1f} s, bake {secs.get('bake', 0):.1f} s "
            f"(numba {rec.get('numba') or 'none'}, {shading} shading), "
            f"bake again {secs.get('bake_again', 0):.1f} s, draw handler ok, "
            f"render {len(rec.get('preview', {})) - 1} modes, "
            f"export {rec.get('glb_bytes', 0) / 1e6:.2f} MB, page {steps.get('page', 'not opened')}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="./prtt.sh compat", description=__doc__.split("\n\n")[0])
    ap.add_argument("versions", nargs="*", metavar="VERSION",
                    help=f"Blender versions or lines (default: {' '.join(DEFAULT)}; 'all': {' '.join(RELEASES)})")
    ap.add_argument("--json", metavar="FILE", help="write every result to FILE")
    ap.add_argument("--work", metavar="DIR", help="keep each version's scene, textures and log in DIR "
                                                  "(default: a temporary folder, removed)")
    ap.add_argument("--no-page", action="store_true", help="do not open the exports in the web viewer")
    ap.add_argument("--timeout", type=float, default=900.0, help="seconds one version's chain may take")
    ap.add_argument("--bench", action="store_true",
                    help="instead of the chain: the demo's default bake through the zip in each Blender "
                         "against the development venv (tools/compat_bench.py)")
    args = ap.parse_args(argv)
    names = args.versions or list(DEFAULT)
    if names == ["all"]:
        names = list(RELEASES)
    versions = [release(v) for v in names]
    work = args.work or tempfile.mkdtemp(prefix="prtt-compat-")
    os.makedirs(work, exist_ok=True)

    def log(msg):
        print(msg, file=sys.stderr, flush=True)

    with concurrent.futures.ThreadPoolExecutor(4) as pool:   # downloads: network-bound
        pythons = dict(zip(versions, pool.map(lambda v: venv(v, log), versions)))
    zip_path = build_zip(work)
    log(f"[compat] {os.path.basename(zip_path)}; each version's log under {work}")
    if args.bench:
        records = bench(versions, pythons, zip_path, work, args.timeout)
        if args.json:
            with open(args.json, "w", encoding="utf-8") as f:
                json.dump({"zip": os.path.basename(zip_path), "bench": records}, f, indent=1)
        if not args.work:
            shutil.rmtree(work, ignore_errors=True)
        return 1 if any("error" in r for r in records.values()) else 0
    site = None if args.no_page else Site(os.path.join(work, "site"))
    results = {}
    try:
        for v in versions:
            rec = run_chain(pythons[v], zip_path, os.path.join(work, v), args.timeout)
            if site is not None and rec.get("glb"):
                try:
                    rec["steps"]["page"] = open_page(site, rec["glb"], f"{v}.glb")
                except Exception as exc:          # noqa: BLE001 - the page's failure is this version's result
                    rec["steps"]["page"] = f"{type(exc).__name__}: {exc}"[:300]
                if not rec["steps"]["page"].startswith("ok"):
                    rec["steps"]["page"] = "FAIL " + rec["steps"]["page"]
            results[v] = rec
            print(summary(v, rec), flush=True)
    finally:
        if site is not None:
            site.close()
    failed = [v for v, r in results.items()
              if any(not (s == "ok" or s.startswith("ok ")) for s in r["steps"].values())]
    textures = compare_textures(results, work)
    if textures is not None:
        print("textures: " + textures["summary"], flush=True)
    if args.json:
        with open(args.json, "w", encoding="utf-8") as f:
            json.dump({"zip": os.path.basename(zip_path), "textures": textures,
                       "zip_sha256": hashlib.sha256(open(zip_path, "rb").read()).hexdigest(),
                       "results": results}, f, indent=1)
    if not args.work:
        shutil.rmtree(work, ignore_errors=True)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
