"""One shading source for both hosts (issue 34): the web viewer's
viewer/prtt_shaders.js describes each shader variant (files, defines,
resources) exactly as core/preview/shader_source.py describes it to
Blender's GPUShaderCreateInfo, and wraps the same shaders/*.glsl texts.
Node runs the module (it imports nothing) and prints its descriptions."""
import json
import pathlib
import shutil
import subprocess

import pytest

from prtt_addon.core.preview import shader_source as ss

ROOT = pathlib.Path(__file__).resolve().parent.parent
NODE = shutil.which("node")
pytestmark = pytest.mark.skipif(NODE is None, reason="node is not installed: the viewer's JavaScript cannot run")
URL = (ROOT / "viewer" / "prtt_shaders.js").as_uri()


def js(body: str):
    script = f"import * as S from {json.dumps(URL)};\nconst out = (x) => process.stdout.write(JSON.stringify(x));\n{body}"
    proc = subprocess.run([NODE, "--input-type=module", "-e", script], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return json.loads(proc.stdout)


def as_lists(t):
    return [list(x) if isinstance(x, tuple) else x for x in t]


def test_surface_variants_are_blenders():
    cases = [(mode, bands, bounce, display, sun) for mode in ss.FRAGMENT_MODES for bands in (1, 3, 5, 8)
             for bounce in (False, True) for display in (False, True) for sun in (False, True)]
    got = js(f"out({json.dumps(cases)}.map(([m, b, bo, d, s]) => S.surfaceVariant(m, b, "
             f"{{bounce: bo, display: d, sun: s, gauntNnz: m === 'tp' ? {{1: {ss.gaunt_nnz(1)}, 3: {ss.gaunt_nnz(3)}, "
             f"5: {ss.gaunt_nnz(5)}, 8: {ss.gaunt_nnz(8)}}}[b] : 0}})));")
    for (mode, bands, bounce, display, sun), v in zip(cases, got):
        ref = ss.variant(mode, bands, bounce=bounce, display=display, sun=sun)
        assert v["name"] == ref.name
        assert v["defines"] == as_lists(ref.defines), (mode, bands, bounce)
        assert v["typedefs"].split() == ref.typedefs.split()
        assert v["vertexIn"] == as_lists(ref.vertex_in)
        assert v["interface"] == as_lists(ref.interface)
        assert v["samplers"] == as_lists(ref.samplers)
        assert v["uniformBufs"] == as_lists(ref.uniform_bufs)
        assert v["pushConstants"] == as_lists(ref.push_constants)
        assert v["vertexFiles"] == list(ref.vertex_files)
        assert v["fragmentFiles"] == list(ref.fragment_files)


def test_relight_variants_are_blenders():
    cases = [(b, g, sh) for b in (1, 3, 5, 8) for g in range(0, b + 1) for sh in (False, True)]
    got = js(f"out({json.dumps(cases)}.map(([b, g, sh]) => S.relightVariant(b, g, sh)));")
    for (b, g, sh), v in zip(cases, got):
        ref = ss.relight_variant(b, g, sh)
        assert v["name"] == ref.name
        assert v["defines"] == as_lists(ref.defines)
        assert v["typedefs"].split() == ref.typedefs.split()
        assert v["samplers"] == as_lists(ref.samplers)
        assert v["uniformBufs"] == as_lists(ref.uniform_bufs)
        assert v["pushConstants"] == as_lists(ref.push_constants)
        assert v["vertexFiles"] == list(ref.vertex_files) and v["fragmentFiles"] == list(ref.fragment_files)


def test_the_web_sources_hold_the_shared_files_verbatim():
    """The WebGL2 text of a variant contains every shaders/ file it names,
    unchanged, in order: the page adds declarations, never a second formula."""
    files = sorted({f for m in ss.FRAGMENT_MODES for f in ss.variant(m, 5, bounce=True).fragment_files
                    + ss.variant(m, 5, bounce=True).vertex_files})
    texts = {f: ss.read_source(f) for f in files}
    got = js(f"const T = {json.dumps(texts)};\n"
             "const G = [[1, 0, 0], [0, 0, -1], [0, 1, 0]];\n"
             "out(S.MODES.map((m) => S.surfaceSources(S.surfaceVariant(m, 5, {bounce: true, gauntNnz: 10}), "
             "(f) => T[f], G)));")
    for mode, src in zip(ss.FRAGMENT_MODES, got):
        ref = ss.variant(mode, 5, bounce=True)
        for stage, names in (("vertexShader", ref.vertex_files), ("fragmentShader", ref.fragment_files)):
            at = 0
            for f in names:
                i = src[stage].find(texts[f], at)
                assert i >= 0, (mode, stage, f)
                at = i + len(texts[f])


def test_the_depth_prepass_variant_is_blenders():
    v = js("out(S.depthVariant());")
    ref = ss.depth_variant()
    assert v["name"] == ref.name and v["defines"] == as_lists(ref.defines)
    assert v["typedefs"].split() == ref.typedefs.split()
    assert v["vertexIn"] == as_lists(ref.vertex_in) and v["uniformBufs"] == as_lists(ref.uniform_bufs)
    assert v["pushConstants"] == as_lists(ref.push_constants)
    assert v["vertexFiles"] == list(ref.vertex_files) and v["fragmentFiles"] == list(ref.fragment_files)
