"""Seed corpora for the fuzz harnesses: real files the project writes.

:func:`write_seeds` bakes a tiny scene twice (relightable and baked bounces,
per-vertex transfer, half and float storage) and keeps what a user's folder
holds: the job file, manifest.json, transfer/bounce/relight EXRs, the
vertex and generated-UV side files; plus environment images (a Blender
studio light made small, as .exr and as run-length encoded Radiance .hdr),
the worker's event lines of a real bake, KTX2 payloads of the baked planes
(core.io.gltf_prtt) and a .glb carrying the PRTT extension's JSON.
"""
from __future__ import annotations

import json
import os
import shutil
import struct
import tempfile

import numpy as np

#: Target name -> subfolder of the corpus (one per harness).
SEED_KINDS = ("job", "manifest", "exr", "sidecar", "env", "world", "events", "ktx2", "glb")


def seed_scene(resolution: int = 8):
    from ...core.model.scene import Scene
    from ..bench import meshgen as mg
    floor = mg.plane(4.0, subdiv=1)
    box = mg.box((1.0, 1.0, 1.0), (0.0, 0.0, 0.5))
    p = floor.vertices[:, :2]
    floor_uv = ((p - p.min(0)) / (p.max(0) - p.min(0)))[floor.faces]
    parts = [(floor, floor_uv), (box, mg.box_face_uvs(box))]
    return Scene(positions=np.concatenate([m.corner_positions() for m, _ in parts]),
                 normals=np.concatenate([m.corner_normals() for m, _ in parts]),
                 uvs=np.concatenate([u for _, u in parts]),
                 set_id=np.concatenate([np.full(m.n_faces, i) for i, (m, _) in enumerate(parts)]),
                 set_names=["floor", "box"], set_resolution=np.array([[resolution] * 2] * 2),
                 object_id=np.concatenate([np.full(m.n_faces, i) for i, (m, _) in enumerate(parts)]),
                 object_names=["floor", "box"])


def _rgbe(rgb: np.ndarray) -> np.ndarray:
    """(H, W, 3) float -> (H, W, 4) uint8 RGBE (Ward)."""
    m = rgb.max(axis=2)
    e = np.where(m > 1e-32, np.floor(np.log2(np.maximum(m, 1e-32))) + 1, 0)
    scale = np.where(m > 1e-32, 256.0 / np.exp2(e), 0.0)
    out = np.zeros(rgb.shape[:2] + (4,), np.uint8)
    out[..., :3] = np.clip(rgb * scale[..., None], 0, 255).astype(np.uint8)
    out[..., 3] = np.where(m > 1e-32, e + 128, 0).astype(np.uint8)
    return out


def radiance_bytes(rgb: np.ndarray) -> bytes:
    """A Radiance .hdr of (H, W, 3) ``rgb`` with new-style run-length scanlines
    (runs where a component repeats, literals elsewhere)."""
    h, w, _ = rgb.shape
    px = _rgbe(rgb)
    out = bytearray(b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n" + f"-Y {h} +X {w}\n".encode())
    for row in px:
        out += bytes([2, 2, w >> 8, w & 255])
        for c in range(4):
            comp, i = row[:, c], 0
            while i < w:
                j = i
                while j < w and j - i < 127 and comp[j] == comp[i]:
                    j += 1
                if j - i >= 3:
                    out += bytes([128 + j - i, int(comp[i])])
                    i = j
                    continue
                j = i
                while j < w and j - i < 128 and not (j + 2 < w and comp[j] == comp[j + 1] == comp[j + 2]):
                    j += 1
                j = max(j, i + 1)
                out += bytes([j - i]) + comp[i:j].tobytes()
                i = j
    return bytes(out)


def _glb(doc: dict, blob: bytes) -> bytes:
    js = json.dumps(doc).encode()
    js += b" " * (-len(js) % 4)
    blob += b"\0" * (-len(blob) % 4)
    total = 12 + 8 + len(js) + 8 + len(blob)
    return (struct.pack("<4sII", b"glTF", 2, total) + struct.pack("<II", len(js), 0x4E4F534A) + js
            + struct.pack("<II", len(blob), 0x004E4942) + blob)


def write_seeds(root: str) -> dict[str, list[str]]:
    """Write the seed files under ``root``/<kind>/; returns {kind: [paths]}."""
    from ...core.bake.pipeline.context import BakeSettings
    from ...core.bake.pipeline.runner import bake_scene
    from ...core.io.exr_io import read_relight_exr, read_sh_exr
    from ...core.io.gltf_prtt import relight_dc_payload, root_extension, transfer_payload
    from ...core.io.image_io import read_hdr_image
    from ...core.io.jobfile import save_scene
    from ...core.light.envmap import builtin_environment_path, environment_light

    out: dict[str, list[str]] = {k: [] for k in SEED_KINDS + ("ktx2-specs",)}

    def put(kind: str, name: str, data: bytes) -> None:
        os.makedirs(os.path.join(root, kind), exist_ok=True)
        path = os.path.join(root, kind, name)
        with open(path, "wb") as f:
            f.write(data)
        out[kind].append(path)

    sc = seed_scene()
    light = environment_light(builtin_environment_path("forest"), 5)
    with tempfile.TemporaryDirectory() as tmp:
        job = os.path.join(tmp, "job.npz")
        save_scene(sc, job, extra={"settings": {"rays": 16}, "light": {"coeffs": light.tolist(),
                                                                        "description": "forest"}})
        put("job", "job.npz", open(job, "rb").read())
        events = []
        runs = [("relight", dict(bounces=1, bounce_mode="relightable", vertex_mode=True, tuning="auto")),
                ("baked", dict(bounces=2, bounce_mode="baked", half=False, tuning="fixed", bands=3))]
        for tag, extra in runs:
            folder = os.path.join(tmp, tag)
            bake_scene(sc, folder, BakeSettings(rays=16, bounce_rays=8, **extra), light=light,
                       progress=events.append)
            for name in sorted(os.listdir(folder)):
                data = open(os.path.join(folder, name), "rb").read()
                if name.endswith(".exr"):
                    put("exr", f"{tag}-{name}", data)
                elif name.endswith(".npz"):
                    put("sidecar", f"{tag}-{name}", data)
                elif name == "manifest.json":
                    put("manifest", f"{tag}-{name}", data)
        uvs = {"UVMap": sc.uvs[:4].astype(np.float32), "Other": sc.uvs[4:6].astype(np.float32)}
        g = os.path.join(tmp, "generated_uvs.npz")
        np.savez(g, keys=np.array(sorted(uvs), dtype=str), **{f"uv_{i}": uvs[k] for i, k in enumerate(sorted(uvs))})
        put("sidecar", "generated_uvs.npz", open(g, "rb").read())
        for i, e in enumerate(events[:40] + events[-3:]):
            put("events", f"event{i:03d}.json", json.dumps(e, default=str).encode())

        planes, _ = read_sh_exr(os.path.join(tmp, "relight", "floor.transfer.exr"))
        dc, _glossy, _attrs = read_relight_exr(os.path.join(tmp, "relight", "floor.relight.exr"))
        payloads = {"transfer-zstd.ktx2": transfer_payload(planes.transpose(2, 0, 1)),
                    "transfer-none.ktx2": transfer_payload(planes.transpose(2, 0, 1)[:4], supercompression="none"),
                    "relight-dc-u8.ktx2": relight_dc_payload(dc, encoding="u8")}
        payload, info = payloads["transfer-zstd.ktx2"]
        for name, (blob, meta) in payloads.items():
            put("ktx2", name, blob)
            # What the glTF extension says of each payload (the page's reader checks against it).
            put("ktx2-specs", name + ".json", json.dumps(meta).encode())
        doc = {"asset": {"version": "2.0"}, "extensionsUsed": ["PRTT_radiance_transfer"],
               "buffers": [{"byteLength": len(payload)}],
               "extensions": {"PRTT_radiance_transfer": root_extension(
                   bands=5, light=light, light_description="forest", sets=[{"name": "floor", "transfer": info}])}}
        put("glb", "prtt.glb", _glb(doc, payload))

        # World settings as FuzzedDataProvider reads them: floats, then choices (a default World,
        # a bright rotated one, a coloured one).
        for i, vals in enumerate(([1.0, 0.05, 0.05, 0.05, 0.0, 0.0, 0.0], [30.0, 1, 1, 1, 0.3, -1.2, 2.5],
                                  [0.5, 0.8, 0.4, 0.1, 0.0, 0.0, 3.14])):
            put("world", f"world{i}.bin", struct.pack("<7d", *vals) + bytes([i % 2, 1, i % 2]))
        env = read_hdr_image(builtin_environment_path("forest"))
        small = env[::max(1, env.shape[0] // 16), ::max(1, env.shape[1] // 32)][:16, :32].astype(np.float32)
        put("env", "forest.hdr", radiance_bytes(small))
        from ...core.io.image_write import write_image
        ex = os.path.join(tmp, "forest.exr")
        write_image(ex, np.concatenate([small[::-1], np.ones(small.shape[:2] + (1,), np.float32)], axis=2))
        put("env", "forest.exr", open(ex, "rb").read())
    return out


def ensure_seeds(root: str) -> dict[str, list[str]]:
    """The seeds under ``root`` (written once; delete the folder to remake them)."""
    stamp = os.path.join(root, ".complete")
    if not os.path.exists(stamp) or not all(os.path.isdir(os.path.join(root, k)) for k in SEED_KINDS):
        shutil.rmtree(root, ignore_errors=True)
        write_seeds(root)
        open(stamp, "w").close()
    return {k: sorted(os.path.join(root, k, n) for n in os.listdir(os.path.join(root, k)))
            for k in SEED_KINDS + ("ktx2-specs",) if os.path.isdir(os.path.join(root, k))}
