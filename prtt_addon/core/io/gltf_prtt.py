"""The ``PRTT_radiance_transfer`` glTF extension: what goes into a .glb besides
Blender's own glTF (docs/gltf.md; its JSON schema is
docs/schema/PRTT_radiance_transfer.schema.json).

The root extension holds the SH convention, the frame, the light and one
entry per texture set; each set's transfer planes travel as a KTX2 2D array
texture (core/io/ktx2.py: RGBA16F, coefficient k in layer k // 4, channel
k % 4) in a buffer view of the .glb. A mesh primitive names the TEXCOORD set
that holds its PRTT UVs and the texture set it samples.

Frame: the textures and the light are in Blender's world frame (Z up), as
baked. glTF is Y up: Blender's exporter writes (x, y, z) as (x, z, -y). A
viewer turns a glTF world direction d into the bake frame with
``gltfToBakeFrame`` (d_bake = M d) before evaluating the SH basis.
"""
from __future__ import annotations

import numpy as np

from .ktx2 import ktx2_bytes, sh_layers

NAME = "PRTT_radiance_transfer"
VERSION = 1
#: glTF world direction -> Blender world direction (the inverse of the
#: exporter's Y-up conversion (x, y, z) -> (x, z, -y)).
GLTF_TO_BAKE_FRAME = ((1.0, 0.0, 0.0), (0.0, 0.0, -1.0), (0.0, 1.0, 0.0))


def transfer_payload(planes: np.ndarray, *, supercompression: str = "zstd") -> tuple[bytes, dict]:
    """A set's transfer planes (K, H, W), rows top first, as KTX2 bytes and
    the JSON that describes them (coefficients, layers, the half-float error)."""
    K = planes.shape[0]
    return _payload(sh_layers(np.asarray(planes, np.float32)), "transfer", K, supercompression)


def _payload(layers: np.ndarray, kind: str, K: int, supercompression: str, **meta) -> tuple[bytes, dict]:
    """(layers, H, W, 4) as KTX2 bytes and the JSON every payload carries."""
    L, H, W = layers.shape[:3]
    blob, level_bytes = ktx2_bytes([layers], supercompression=supercompression,
                                   keys={"PRTTkind": kind, "PRTTcoefficients": str(K)})
    return blob, {"coefficients": int(K), **meta, "layers": int(L), "width": int(W), "height": int(H),
                  "format": "RGBA16F", "supercompression": supercompression, "bytes": len(blob),
                  "uncompressedBytes": int(level_bytes[0][1])}


def relight_dc_payload(dc: np.ndarray, *, supercompression: str = "zstd") -> tuple[bytes, dict]:
    """A set's relightable bounce, its DC rows (3, K, H, W): colour c's row over
    light coefficient i, rows top first, as KTX2 bytes (colour c's rows from
    layer c * ceil(K / 4), coefficient i in layer i // 4, channel i % 4 of
    them) and their JSON. The bounce's diffuse radiance under a light L is
    sqrt(4 pi) * sum_i DC_c,i L_c,i per colour c (docs/shading.md)."""
    C, K = dc.shape[:2]
    layers = np.concatenate([sh_layers(np.asarray(dc[c], np.float32)) for c in range(C)])
    return _payload(layers, "relight-dc", K, supercompression, colours=int(C),
                    layersPerColour=int(layers.shape[0] // C))


def root_extension(*, bands: int, light: np.ndarray, light_description: str, sets: list) -> dict:
    """The root extension's JSON, ``sets`` each {"name", "resolution",
    "transfer": {..., "bufferView": <filled by the writer>}}. ``light``:
    (K, 3) RGB SH of the environment in the bake frame (Blender's World at
    export, strength and rotation applied)."""
    L = np.asarray(light, np.float64)
    if L.ndim != 2 or L.shape[1] != 3 or L.shape[0] != bands * bands:
        raise ValueError(f"light: expected ({bands * bands}, 3) SH coefficients, got {L.shape}")
    return {
        "version": VERSION,
        "sh": {"bands": int(bands), "coefficients": int(bands * bands), "index": "k = l*l + l + m",
               "basis": "real orthonormal, Condon-Shortley phase (docs/sh-conventions.md)",
               "frame": "Blender world, Z up", "gltfToBakeFrame": [list(r) for r in GLTF_TO_BAKE_FRAME]},
        "light": {"description": light_description, "rgb": L.round(9).tolist()},
        "sets": sets,
    }
