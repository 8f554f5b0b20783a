"""The fuzz harnesses (issue #36, prtt_addon/dev/fuzz, docs/fuzzing.md).

CI runs every harness for a short fixed budget from its seeds and saved
inputs (not the grown corpus of a developer's machine), replays every input
that once broke a reader (tests/fuzz_corpus/<target>/), and checks that a
crash put back into a reader is found within that budget.
"""
import json
import os
import re
import shutil
import subprocess
import sys
import time

import pytest

from prtt_addon.dev.fuzz import targets
from prtt_addon.dev.fuzz.seeds import ensure_seeds

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SAVED = os.path.join(ROOT, "tests", "fuzz_corpus")
#: Executions each harness gets in CI (the slowest, exr, runs ~400 a second).
CI_RUNS = 3000

pytest.importorskip("atheris")


@pytest.fixture(scope="module")
def corpus(tmp_path_factory):
    root = tmp_path_factory.mktemp("fuzz")
    ensure_seeds(str(root / "seeds"))
    return root


def fuzz(corpus, *args, pythonpath=ROOT):
    env = dict(os.environ, PYTHONPATH=pythonpath)
    out = corpus / f"report-{time.monotonic_ns()}.json"
    t0 = time.perf_counter()
    r = subprocess.run([sys.executable, "-m", "prtt_addon.dev.fuzz", *args, "--fresh", "--corpus", str(corpus),
                        "--json", str(out)], capture_output=True, text=True, env=env, timeout=900, cwd=pythonpath)
    return r, json.loads(out.read_text())["reports"], time.perf_counter() - t0


def test_seeds_are_real_files_every_reader_accepts(corpus):
    """Every seed kind exists and each target takes its seeds without a complaint."""
    seeds = ensure_seeds(str(corpus / "seeds"))
    for name, t in targets.TARGETS.items():
        assert seeds.get(t.seeds), name
        assert targets.quick_check(name, seeds[t.seeds]) >= 1


#: exr-bands decodes each input's rows in child processes (tens of inputs a second, each a few
#: process starts: seconds under a loaded suite): a smaller budget and a longer bound an input.
SLOW = {"exr-bands": (300, 10)}


@pytest.mark.parametrize("name", list(targets.TARGETS))
def test_each_harness_runs_its_ci_budget_clean(corpus, name):
    runs, timeout = SLOW.get(name, (CI_RUNS, 1))
    r, reports, _ = fuzz(corpus, name, "--runs", str(runs), "--timeout", str(timeout))
    rep = reports[0]
    assert r.returncode == 0 and not rep["findings"], r.stdout + rep.get("log", "")
    assert rep["executions"] >= runs and rep["peak_rss_mb"] < 2048


def saved_inputs():
    """(target, path) for each saved input and each target that reads its kind
    (a saved exr input goes through exr and exr-bands)."""
    return [(name, os.path.join(SAVED, kind, f)) for kind in sorted(os.listdir(SAVED))
            for name, t in targets.TARGETS.items() if kind in (name, t.seeds)
            for f in sorted(os.listdir(os.path.join(SAVED, kind)))]


@pytest.mark.parametrize("target, path", saved_inputs(), ids=lambda v: os.path.basename(str(v)))
def test_inputs_that_once_broke_a_reader(target, path):
    """Each saved input gets the reader's declared error (or a result), never a crash."""
    with open(path, "rb") as f:
        targets.TARGETS[target].run(f.read())


def test_damaged_exrs_are_texture_errors_from_the_dc_reader(tmp_path):
    """read_dc_plane decodes in a child: OpenEXR's legacy reader crashed the
    process on these files (a segmentation fault, which inside Blender ends Blender)."""
    from prtt_addon.core.io.exr_io import TextureError, read_dc_plane
    for name in sorted(os.listdir(os.path.join(SAVED, "exr"))):
        p = tmp_path / name
        shutil.copy(os.path.join(SAVED, "exr", name), p)
        with pytest.raises(TextureError, match=re.escape(str(p))):
            read_dc_plane(p)


def test_a_decoder_that_dies_by_a_signal_is_a_texture_error(corpus, monkeypatch):
    """The child that decodes the AO channel killed by SIGSEGV (what the legacy
    reader did in process on tests/fuzz_corpus/exr's files): the reader says so
    in a TextureError naming the file, and the caller's process lives on."""
    from prtt_addon.core.io import exr_io
    good = [p for p in ensure_seeds(str(corpus / "seeds"))["exr"] if p.endswith(".transfer.exr")][0]
    assert exr_io.read_dc_plane(good).shape == (8, 8)
    monkeypatch.setattr(exr_io, "_DC_CHILD", "import os, signal; os.kill(os.getpid(), signal.SIGSEGV)")
    with pytest.raises(exr_io.TextureError, match=r"crashed \(signal 11\)") as e:
        exr_io.read_dc_plane(good)
    assert good in str(e.value)


def test_a_crash_put_back_is_found_within_the_ci_budget(corpus, tmp_path):
    """The Radiance run-length decoder without its check that a literal run
    fits the scanline: numpy's broadcast error escapes (a ValueError that is
    not ImageReadError). The env harness finds it within CI_RUNS executions."""
    copy = tmp_path / "src"
    shutil.copytree(os.path.join(ROOT, "prtt_addon"), copy / "prtt_addon",
                    ignore=shutil.ignore_patterns("__pycache__"))
    src = copy / "prtt_addon" / "core" / "io" / "image_io.py"
    text = src.read_text()
    check = "if count == 0 or x + count > w or pos + count > n:"
    assert check in text
    src.write_text(text.replace(check, "if count == 0 or pos + count > n:"))
    r, reports, seconds = fuzz(corpus, "env", "--runs", str(CI_RUNS), pythonpath=str(copy))
    rep = reports[0]
    assert r.returncode == 1 and rep["findings"], r.stdout
    print(f"planted crash found after {rep['executions']} executions, {seconds:.1f} s")
    with open(rep["findings"][0], "rb") as f:
        data = f.read()
    targets.TARGETS["env"].run(data)          # the real decoder refuses it cleanly


def test_the_pages_readers_take_their_ci_budget_clean(corpus):
    """viewer/prtt_env.js and viewer/prtt_textures.js's KTX2 reader on 3000 mutants in node."""
    from prtt_addon.dev.fuzz import page
    if shutil.which("node") is None:
        pytest.skip("node is not installed")
    r = page.run(ensure_seeds(str(corpus / "seeds")), CI_RUNS)
    assert r["executions"] == CI_RUNS and not r["findings"] and not r["hangs"], (r["findings"][:5], r["hangs"][:5])
    assert r["accepted"] > CI_RUNS // 50         # the mutants reach the decoders, not only the magic checks
    assert r["slowest_ms"] < 1000


def test_a_page_reader_that_forgets_the_file_name_is_found(corpus, tmp_path):
    """The page's Radiance decoder with one message that no longer names the
    file (the page shows it to the user): found within the CI budget."""
    from prtt_addon.dev.fuzz import page
    if shutil.which("node") is None:
        pytest.skip("node is not installed")
    viewer = tmp_path / "viewer"
    shutil.copytree(os.path.join(ROOT, "viewer"), viewer)
    src = viewer / "prtt_env.js"
    text = src.read_text()
    line = "throw new Error(`${name}: truncated Radiance run-length data`)"
    assert line in text
    src.write_text(text.replace(line, "throw new Error('truncated Radiance run-length data')"))
    r = page.run(ensure_seeds(str(corpus / "seeds")), CI_RUNS, viewer=str(viewer))
    assert r["findings"] and all("Error: truncated Radiance run-length data" in f for f in r["findings"])
    print(f"planted page bug found {len(r['findings'])} times in {CI_RUNS} mutants")


def test_an_environment_that_hangs_is_contained_as_the_page_contains_it(corpus, tmp_path):
    """In the page harness (as in the page) an environment decodes in a worker
    that is ended after its limit: an input on which the decoder loops (planted
    here: the page's own header walk now refuses the inputs that made three's
    EXRLoader loop) is reported as a hang, and the inputs after it in the
    bundle still run (a good .hdr seed is accepted)."""
    from prtt_addon.dev.fuzz import page
    if shutil.which("node") is None:
        pytest.skip("node is not installed")
    viewer = tmp_path / "viewer"
    shutil.copytree(os.path.join(ROOT, "viewer"), viewer)
    src = viewer / "prtt_env.js"
    head = "export async function environmentFromBytes(bytes, name, bands) {\n"
    text = src.read_text()
    assert head in text
    src.write_text(text.replace(head, head + "  if (bytes.length === 7) for (;;) { /* planted */ }\n"))
    seeds = ensure_seeds(str(corpus / "seeds"))
    good = [p for p in seeds["env"] if p.endswith(".hdr")][0]
    with open(good, "rb") as f:
        hdr = f.read()
    t0 = time.perf_counter()
    r, why = page.run_bundle([("env", hdr, None), ("env", b"#?loop", None), ("env", b"#?loops", None),
                              ("env", hdr, None)], str(tmp_path / "bundle.bin"), viewer=str(viewer))
    assert r is not None, why
    assert r["hangs"] == [2] and r["accepted"] == 2 and not r["failures"], r
    print(f"hang contained; bundle of 4 in {time.perf_counter() - t0:.1f} s")


def test_the_exrs_that_hung_three_are_refused_at_once(tmp_path):
    """tests/fuzz_corpus/page-hang: EXRs on which three's EXRLoader never
    returns. The page's header walk refuses each with an Error naming it,
    without a hang (run in the page harness's worker: 5 s a file)."""
    from prtt_addon.dev.fuzz import page
    if shutil.which("node") is None:
        pytest.skip("node is not installed")
    folder = os.path.join(SAVED, "page-hang")
    items = []
    for n in sorted(os.listdir(folder)):
        with open(os.path.join(folder, n), "rb") as f:
            items.append(("env", f.read(), None))
    r, why = page.run_bundle(items, str(tmp_path / "bundle.bin"))
    assert r is not None, why
    assert not r["hangs"] and not r["failures"] and r["accepted"] == 0 and r["slowest_ms"] < 1000, r
