"""The KTX2 writer (core/io/ktx2.py, issue 34) against an independent
implementation: ktx-parse (npm, tools/js) parses every file, and its own
writer, given the container it parsed, lays out the very same bytes."""
import hashlib
import json
import os
import shutil
import subprocess

import numpy as np
import pytest

from prtt_addon.core.io.ktx2 import KTX2Error, read_ktx2, sh_layers, write_ktx2

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
JS = os.path.join(ROOT, "tools", "js")


def node(script, *args):
    exe = shutil.which("node")
    assert exe and os.path.isdir(os.path.join(JS, "node_modules", "ktx-parse")), \
        "Node.js and tools/js/node_modules (ktx-parse) are needed: ./prtt.sh installs them (npm ci)"
    r = subprocess.run([exe, os.path.join(JS, script), *map(str, args)], capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 0, r.stderr
    return r.stdout


def chain(rng, layers, h, w, levels):
    out = []
    for i in range(levels):
        out.append((rng.standard_normal((layers, max(1, h >> i), max(1, w >> i), 4)) * 10).astype(np.float16))
    return out


CASES = [(1, 1, 1, 1, "none"), (7, 8, 16, 2, "none"), (7, 5, 3, 3, "zstd"), (4, 33, 17, 6, "none"),
         (9, 64, 64, 1, "zstd")]


@pytest.mark.parametrize("layers, h, w, n, scheme", CASES)
def test_ktx_parse_reads_it_and_writes_the_same_bytes(tmp_path, rng, layers, h, w, n, scheme):
    levels = chain(rng, layers, h, w, n)
    path = tmp_path / "t.ktx2"
    info = write_ktx2(path, levels, supercompression=scheme, keys={"PRTTkind": "transfer"})
    data = path.read_bytes()
    assert info["bytes"] == len(data)
    c = json.loads(node("ktx_info.mjs", path))
    assert (c["vkFormat"], c["typeSize"], c["pixelWidth"], c["pixelHeight"], c["pixelDepth"], c["layerCount"],
            c["faceCount"]) == (97, 2, w, h, 0, layers, 1)
    assert c["supercompressionScheme"] == {"none": 0, "zstd": 2}[scheme]
    (dfd,) = c["dfd"]
    assert (dfd["colorModel"], dfd["colorPrimaries"], dfd["transferFunction"], dfd["bytesPlane"][0]) == (1, 1, 1, 8)
    assert [(s["bitOffset"], s["bitLength"], s["channelType"]) for s in dfd["samples"]] == \
        [(0, 15, 0xC0), (16, 15, 0xC1), (32, 15, 0xC2), (48, 15, 0xCF)]
    assert c["keyValue"]["KTXorientation"] == "rd" and c["keyValue"]["PRTTkind"] == "transfer"
    assert len(c["levels"]) == n
    for lv, mine, (stored, raw) in zip(c["levels"], levels, info["level_bytes"]):
        assert lv["uncompressed"] == raw == mine.nbytes and lv["bytes"] == stored
        if scheme == "none":
            assert lv["sha256"] == hashlib.sha256(mine.tobytes()).hexdigest()
    node("ktx_rewrite.mjs", path, tmp_path / "again.ktx2")
    assert (tmp_path / "again.ktx2").read_bytes() == data
    back, keys = read_ktx2(path)
    assert keys["PRTTkind"] == "transfer"
    for a, b in zip(back, levels):
        assert a.dtype == np.float16 and np.array_equal(a.view(np.uint16), b.view(np.uint16))


def test_sh_layers_put_coefficient_k_in_layer_k_over_4():
    K, H, W = 25, 3, 5
    planes = np.arange(K * H * W, dtype=np.float32).reshape(K, H, W)
    L = sh_layers(planes)
    assert L.shape == (7, H, W, 4)
    for k in range(K):
        assert np.array_equal(L[k // 4, :, :, k % 4], planes[k])
    assert not L[6, :, :, 1:].any()


def test_half_storage_error_is_within_its_bound(rng):
    """float16 keeps 11 significant bits: relative error <= 2^-11 over the
    normal half range (6.1e-5 .. 65504)."""
    x = np.exp(rng.uniform(np.log(6.2e-5), np.log(6.5e4), 100_000)) * rng.choice([-1.0, 1.0], 100_000)
    rel = np.abs(x.astype(np.float16).astype(np.float64) - x) / np.abs(x)
    assert rel.max() <= 2.0 ** -11


@pytest.mark.parametrize("levels, message", [
    ([], "1..15 mip levels"),
    ([np.zeros((2, 4, 4, 3), np.float16)], "expected (layers, height, width, 4)"),
    ([np.zeros((2, 4, 4, 4), np.int32)], "expected floats or uint8"),
    ([np.zeros((2, 4, 4, 4)), np.zeros((2, 4, 4, 4))], "level 1: expected shape (2, 2, 2, 4)"),
    ([np.zeros((3000, 1, 1, 4))], "at most 2048 layers"),
])
def test_bad_levels_are_refused_and_nothing_is_written(tmp_path, levels, message):
    with pytest.raises(KTX2Error, match=message.replace("(", r"\(").replace(")", r"\)")):
        write_ktx2(tmp_path / "x.ktx2", levels)
    assert not os.listdir(tmp_path)


def test_reader_refuses_damaged_files(tmp_path, rng):
    path = tmp_path / "ok.ktx2"
    write_ktx2(path, chain(rng, 3, 8, 8, 2))
    data = path.read_bytes()
    bad = tmp_path / "bad.ktx2"
    cases = {
        "truncated": data[:len(data) // 2],
        "header only": data[:40],
        "not ktx": b"PNG" + data[3:],
        "other format": data[:12] + (37).to_bytes(4, "little") + data[16:],
        "huge layers": data[:32] + (10 ** 9).to_bytes(4, "little") + data[36:],
        "two faces": data[:36] + (2).to_bytes(4, "little") + data[40:],
        "level past the end": data[:80] + (len(data) + 10).to_bytes(8, "little") + data[88:],
    }
    for what, blob in cases.items():
        bad.write_bytes(blob)
        with pytest.raises(KTX2Error, match="bad.ktx2"):
            read_ktx2(bad)
        assert what


def test_reader_refuses_lying_sizes_before_allocating(tmp_path):
    """A header claiming a huge array, and a Zstandard frame declaring 2^50
    bytes: KTX2Error, never a MemoryError or a memory-limit error from deep
    inside (found by review)."""
    import struct

    from prtt_addon.core.io.ktx2 import ktx2_bytes, parse_ktx2
    blob = bytearray(ktx2_bytes([np.zeros((1, 4, 4, 4), np.float16)], supercompression="zstd")[0])
    off, ln, raw = struct.unpack_from("<3Q", blob, 80)
    frame = struct.pack("<I", 0xFD2FB528) + bytes([(3 << 6) | (1 << 5)]) + struct.pack("<Q", 1 << 50) + bytes([1, 0, 0])
    lying = bytearray(bytes(blob[:off]) + frame)
    struct.pack_into("<3Q", lying, 80, off, len(frame), raw)
    with pytest.raises(KTX2Error, match="declares"):
        parse_ktx2(bytes(lying))
    huge = bytearray(ktx2_bytes([np.zeros((1, 4, 4, 4), np.float16)])[0])
    struct.pack_into("<3I", huge, 20, 16384, 16384, 0)          # width, height, depth
    struct.pack_into("<I", huge, 32, 2048)                      # layers
    with pytest.raises(KTX2Error):
        parse_ktx2(bytes(huge))


@pytest.mark.parametrize("scheme", ["none", "zstd"])
def test_rgba8_files_are_ktx_parses_too(tmp_path, rng, scheme):
    """The glTF export's 8-bit encoding: VK_FORMAT_R8G8B8A8_UNORM (37), typeSize
    1, a DFD of four 8-bit unsigned normalised samples; ktx-parse reads it and
    writes the very same bytes, the reader gives the bytes back."""
    levels = [rng.integers(0, 256, (7, 9, 13, 4), dtype=np.uint8)]
    path = tmp_path / "u8.ktx2"
    write_ktx2(path, levels, supercompression=scheme)
    c = json.loads(node("ktx_info.mjs", path))
    assert (c["vkFormat"], c["typeSize"], c["pixelWidth"], c["pixelHeight"], c["layerCount"]) == (37, 1, 13, 9, 7)
    (dfd,) = c["dfd"]
    assert dfd["bytesPlane"][0] == 4
    assert [(s["bitOffset"], s["bitLength"], s["channelType"]) for s in dfd["samples"]] == \
        [(0, 7, 0), (8, 7, 1), (16, 7, 2), (24, 7, 15)]
    assert c["levels"][0]["uncompressed"] == levels[0].nbytes
    node("ktx_rewrite.mjs", path, tmp_path / "again.ktx2")
    assert (tmp_path / "again.ktx2").read_bytes() == path.read_bytes()
    back, _ = read_ktx2(path)
    assert back[0].dtype == np.uint8 and np.array_equal(back[0], levels[0])


@pytest.mark.parametrize("layers, h, w, n, scheme", [(1, 5, 7, 1, "none"), (1, 64, 48, 1, "zstd"), (2, 9, 6, 3, "none")])
def test_one_channel_r8_masks_round_trip_through_ktx_parse(tmp_path, rng, layers, h, w, n, scheme):
    """R8 UNORM (a sun mask's format in the glTF, issue 48): ktx-parse reads
    the format, one 8-bit sample, the sizes, and writes the same bytes."""
    levels = [rng.integers(0, 256, (layers, max(1, h >> i), max(1, w >> i), 1), dtype=np.uint8) for i in range(n)]
    path = tmp_path / "m.ktx2"
    info = write_ktx2(path, levels, supercompression=scheme)
    data = path.read_bytes()
    c = json.loads(node("ktx_info.mjs", path))
    assert (c["vkFormat"], c["typeSize"], c["pixelWidth"], c["pixelHeight"], c["layerCount"]) == (9, 1, w, h, layers)
    (dfd,) = c["dfd"]
    assert dfd["bytesPlane"][0] == 1
    assert [(s["bitOffset"], s["bitLength"], s["channelType"]) for s in dfd["samples"]] == [(0, 7, 0)]
    for lv, mine, (stored, raw) in zip(c["levels"], levels, info["level_bytes"]):
        assert lv["uncompressed"] == raw == mine.nbytes and lv["bytes"] == stored
    node("ktx_rewrite.mjs", path, tmp_path / "again.ktx2")
    assert (tmp_path / "again.ktx2").read_bytes() == data
    back, _ = read_ktx2(path)
    for a, b in zip(back, levels):
        assert a.dtype == np.uint8 and np.array_equal(a, b)


def test_a_sun_payload_is_r8_alone_and_rgba16f_with_its_edges(rng):
    """gltf_prtt.sun_payload: the mask alone as R8 (q = round(255 m), the
    largest rounding said), with edges the (mask, d, valid, h) halves the
    preview uploads (pack.PreviewSet.load_sun_texture's order); bad edges
    are refused, not written."""
    from prtt_addon.core.io.gltf_prtt import sun_payload
    from prtt_addon.core.io.ktx2 import parse_ktx2
    mask = rng.random((6, 9)).astype(np.float32)
    blob, meta = sun_payload(mask)
    (q,), keys = parse_ktx2(blob)
    assert meta["format"] == "R8" and keys["PRTTkind"] == "sun_mask" and q.shape == (1, 6, 9, 1)
    assert np.array_equal(q[0, ..., 0], np.rint(mask * 255).astype(np.uint8))
    assert abs(meta["maxError"] - np.abs(q[0, ..., 0] / 255.0 - mask).max()) < 1e-9 and meta["maxError"] <= 1 / 510
    edges = np.stack([rng.uniform(-3, 3, (6, 9)), rng.uniform(0, 0.5, (6, 9)),
                      rng.integers(0, 2, (6, 9))], axis=-1).astype(np.float32)
    blob, meta = sun_payload(mask, edges)
    (t,), keys = parse_ktx2(blob)
    assert meta["format"] == "RGBA16F" and keys["PRTTkind"] == "sun_mask_edges" and t.dtype == np.float16
    want = np.stack([mask, edges[..., 0], edges[..., 2], edges[..., 1]], axis=-1).astype(np.float16)
    assert np.array_equal(t[0], want)
    assert meta["maxError"] == float(np.abs(want[..., 0].astype(np.float64) - mask).max()) <= 2 ** -11
    for bad in (edges[:5], np.where(edges == edges[0, 0, 0], np.nan, edges), edges * 1e6):
        with pytest.raises(ValueError):
            sun_payload(mask, bad)
