"""One fuzz target per reader of outside data: the bytes of a file (or a
line) in, the reader's result or one of its declared errors out.

A target raises only when the reader misbehaves: an exception that is not
the reader's declared error, a declared error that does not name the file,
or a result of the wrong shape. libFuzzer (atheris) reports those as
crashes; inputs over 1 s or past the RSS bound as timeouts and OOMs.

Every target writes the input to one file per process on a RAM disk when
the reader takes a path, the way a user's folder hands it over.
"""
from __future__ import annotations

import dataclasses
import os
import tempfile
from typing import Callable

import numpy as np


class Misbehaved(AssertionError):
    """A reader answered an input in a way its contract does not allow."""


@dataclasses.dataclass(frozen=True)
class Target:
    name: str
    what: str                         # the reader(s), for the report
    seeds: str                        # seeds.SEED_KINDS entry
    run: Callable[[bytes], None]
    max_len: int                      # libFuzzer -max_len (the seeds are smaller)
    modules: tuple[str, ...]          # what atheris instruments (imported inside instrument_imports)
    prepare: Callable[[], object] | None = None     # one-time set-up before the clock (-timeout) runs


_DIR = None


def scratch(name: str) -> str:
    """A per-process path under /dev/shm (or the temp folder) for ``name``."""
    global _DIR
    if _DIR is None:
        base = "/dev/shm" if os.path.isdir("/dev/shm") and os.access("/dev/shm", os.W_OK) else None
        _DIR = tempfile.mkdtemp(prefix="prtt-fuzz-", dir=base)
    return os.path.join(_DIR, name)


def _put(name: str, data: bytes) -> str:
    path = scratch(name)
    with open(path, "wb") as f:
        f.write(data)
    return path


def declared(path: str, exc: BaseException, kinds: tuple) -> None:
    """Accept ``exc`` if it is one of ``kinds`` and names ``path``; else raise Misbehaved."""
    if not isinstance(exc, kinds):
        raise Misbehaved(f"undeclared {type(exc).__name__}: {exc}") from exc
    if path not in str(exc):
        raise Misbehaved(f"{type(exc).__name__} does not name the file: {exc}") from exc


# --- the readers -----------------------------------------------------------------------

def run_job(data: bytes) -> None:
    """load_scene: the job/scene .npz (headers, members, JSON extra, values)."""
    from ...core.base.memory import MemoryLimitError
    from ...core.io.jobfile import SceneError, load_scene
    path = _put("job.npz", data)
    try:
        sc, extra = load_scene(path)
    except (Exception, MemoryError) as exc:       # noqa: BLE001 - judged by declared()
        declared(path, exc, (SceneError, MemoryLimitError))
        return
    if not isinstance(extra, dict) or sc.n_triangles < 1:
        raise Misbehaved("load_scene returned an empty scene or a non-dict extra")


_PLAN = {}
#: The settings of seeds.write_seeds' "relight" bake: its manifest matches this scene and these settings.
SEED_SETTINGS = dict(rays=16, bounce_rays=8, bounces=1, bounce_mode="relightable", vertex_mode=True, tuning="auto")


def _plan_context():
    """(folder, BakeContext) of the seeds' tiny scene and settings, baked once
    into ``folder``: a manifest that matches lets plan_bake check every file."""
    if "ctx" not in _PLAN:
        from ...core.bake.pipeline.context import BakeContext, BakeSettings
        from ...core.bake.pipeline.runner import bake_scene
        from ...core.light.envmap import builtin_environment_path, environment_light
        from .seeds import seed_scene
        folder = scratch("out")
        light = environment_light(builtin_environment_path("forest"), 5)
        bake_scene(seed_scene(), folder, BakeSettings(**SEED_SETTINGS), light=light)
        _PLAN["ctx"] = (folder, BakeContext.create(seed_scene(), folder, BakeSettings(**SEED_SETTINGS), light=light))
    return _PLAN["ctx"]


def run_manifest(data: bytes) -> None:
    """read_manifest and the "up to date" check that trusts it (plan_bake:
    reuse of transfer and bounce textures, file sizes and hashes), in a
    folder holding the textures of a real bake of the seeds' scene."""
    from ...core.bake.pipeline.plan import plan_bake
    from ...core.base.errors import BakeError
    folder, ctx = _plan_context()
    path = os.path.join(folder, "manifest.json")
    with open(path, "wb") as f:
        f.write(data)
    ctx.warnings.clear()
    try:
        plan_bake(ctx, skip_if_unchanged=True)
    except (Exception, MemoryError) as exc:       # noqa: BLE001
        declared(folder, exc, (BakeError,))


def _exr_readers(data: bytes, fill: bool) -> None:
    from ...core.io.exr_io import TextureError, read_relight_exr, read_sh_exr
    from ...core.preview.pack import relight_operator_layers, transfer_layers
    path = _put("texture.exr", data)

    def layered(opener, **kw):
        src = opener(path, **kw)
        if fill and src.height * src.width <= 1 << 20:
            with src.bands() as bands:
                for band in bands:
                    out = np.empty((band.n, src.width, 4), np.float32)
                    for i in range(min(src.layers, 64)):
                        band.fill_layer(i, out)
    readers = (lambda p: layered(transfer_layers), lambda p: layered(relight_operator_layers, expand=False),
               lambda p: layered(relight_operator_layers))
    if not fill:
        readers = (read_sh_exr, read_relight_exr) + readers
    for reader in readers:
        try:
            reader(path)
        except (Exception, MemoryError) as exc:   # noqa: BLE001
            declared(path, exc, (TextureError,))


def run_exr(data: bytes) -> None:
    """The texture readers of the preview, `render` and the next bake, in
    this process: read_sh_exr, read_relight_exr and the preview's per-layer
    sources (transfer_layers, relight_operator_layers: header, channels,
    attributes). Coverage-guided; the rows the layer sources decode in child
    processes are exr-bands'."""
    _exr_readers(data, fill=False)


def run_exr_bands(data: bytes) -> None:
    """The preview's per-layer sources with their bands filled: the rows are
    decoded in child processes (exr_bands), whose crash or garbage must come
    back as a TextureError naming the file. libFuzzer sees no coverage inside
    a child and each input starts up to three of them (tens of executions a
    second), so this target runs for a time, not to 10^6. read_dc_plane
    decodes in a child process too: its inputs are tests/fuzz_corpus/exr,
    replayed by tests/test_fuzz.py."""
    _exr_readers(data, fill=True)


def run_sidecar(data: bytes) -> None:
    """<set>.vertex.npz and generated_uvs.npz (core.io.sidecars)."""
    from ...core.io.sidecars import SidecarError, read_generated_uvs, read_vertex_transfer
    path = _put("side.npz", data)
    for reader in (read_vertex_transfer, read_generated_uvs):
        try:
            got = reader(path)
        except (Exception, MemoryError) as exc:   # noqa: BLE001
            declared(path, exc, (SidecarError,))
            continue
        arrays = got if isinstance(got, tuple) else tuple(got.values())
        if not all(isinstance(a, np.ndarray) and np.isfinite(a).all() for a in arrays):
            raise Misbehaved(f"{reader.__name__} returned non-finite or non-array values")


def run_env(data: bytes) -> None:
    """Environment images (.exr, Radiance .hdr with its run-length decoding)
    and their SH projection, as a World's image is read."""
    from ...core.base.memory import MemoryLimitError
    from ...core.io.image_io import ImageReadError, read_hdr_image
    from ...core.light.envmap import project_equirect
    path = _put("env.img", data)
    try:
        img = read_hdr_image(path)
    except (Exception, MemoryError) as exc:       # noqa: BLE001
        declared(path, exc, (ImageReadError, MemoryLimitError))
        return
    if img.ndim != 3 or img.shape[2] != 3 or img.dtype != np.float32:
        raise Misbehaved(f"read_hdr_image returned {img.shape} {img.dtype}")
    if img.size <= 1 << 16:
        c = project_equirect(img, 3)
        if not np.isfinite(c).all():
            raise Misbehaved("the projection of a read image is not finite")


_WORLD = {}


def run_world(data: bytes) -> None:
    """A World's settings as the export and the preview turn them into a light
    (envmap.constant_light, mapping_rotation, compose_light): strength, colour,
    the Mapping node's rotation and vector type, any floats including NaN,
    infinities and 1e308. The light is finite and within envmap.LIGHT_MAX, or a
    ValueError says which setting."""
    import atheris

    from ...core.light.envmap import LIGHT_MAX, compose_light, constant_light, mapping_rotation, project_equirect
    if "proj" not in _WORLD:
        rng = np.random.default_rng(5)
        _WORLD["proj"] = project_equirect(rng.random((16, 32, 3)).astype(np.float32) * 3, 3)
    fdp = atheris.FuzzedDataProvider(data)
    strength = fdp.ConsumeFloat()
    colour = [fdp.ConsumeFloat() for _ in range(3)]
    rotation = [fdp.ConsumeFloat() for _ in range(3)]
    vector_type = fdp.PickValueInList(["POINT", "TEXTURE"])
    use_colour = fdp.ConsumeBool()
    try:
        proj = constant_light(colour, 3) if use_colour else _WORLD["proj"]
        R = mapping_rotation(rotation, vector_type) if fdp.ConsumeBool() else None
        L = compose_light(proj, strength, R)
    except ValueError as exc:
        if "World" not in str(exc):
            raise Misbehaved(f"a ValueError that does not say which setting: {exc}") from exc
        return
    if L.shape != (9, 3) or not np.isfinite(L).all() or np.abs(L).max() > LIGHT_MAX:
        raise Misbehaved(f"a light of shape {L.shape} that is not finite from strength {strength}, "
                         f"colour {colour}, rotation {rotation}")


def run_events(data: bytes) -> None:
    """The worker's stdout lines as the Blender side reads them (read_event)."""
    from ...core.base.worker_events import TYPES, read_event
    for line in data.decode("utf-8", "replace").splitlines() or [""]:
        e = read_event(line)
        if e is None:
            continue
        if e["type"] not in TYPES:
            raise Misbehaved(f"unknown type {e['type']!r}")
        if e["type"] == "progress":
            f = e["fraction"]
            if not (isinstance(f, float) and 0.0 <= f <= 1.0 and isinstance(e["stage"], str)
                    and isinstance(e["set"], str)):
                raise Misbehaved(f"progress fields {e!r}")
            f"{e.get('stage')} {e.get('set', '')}".strip()
        if e["type"] in ("warning", "info", "error") and not isinstance(e["message"], str):
            raise Misbehaved("message is not text")
        if e["type"] == "done" and not (isinstance(e["manifest"], str) and isinstance(e["skipped"], bool)):
            raise Misbehaved("done fields")


def run_ktx2(data: bytes) -> None:
    """KTX2 payloads of the glTF export (parse_ktx2: header, level index,
    data format descriptor, key/values, Zstandard)."""
    from ...core.io.ktx2 import KTX2Error, parse_ktx2
    try:
        levels, info = parse_ktx2(data, "payload.ktx2")
    except (Exception, MemoryError) as exc:       # noqa: BLE001
        declared("payload.ktx2", exc, (KTX2Error,))
        return
    if not levels or not all(isinstance(a, np.ndarray) for a in levels) or not isinstance(info, dict):
        raise Misbehaved("parse_ktx2 returned no levels or non-arrays")


def run_glb(data: bytes) -> None:
    """The .glb's JSON chunk (read_glb_json)."""
    from ...core.io.gltf_prtt import read_glb_json
    path = _put("scene.glb", data)
    try:
        read_glb_json(path)
    except (Exception, MemoryError) as exc:       # noqa: BLE001
        declared(path, exc, (ValueError,))


TARGETS = {t.name: t for t in [
    Target("job", "load_scene (.npz job)", "job", run_job, 1 << 15, ("prtt_addon.core.io.jobfile",)),
    Target("manifest", "read_manifest + plan_bake (up-to-date check)", "manifest", run_manifest, 1 << 14,
           ("prtt_addon.core.bake.pipeline.plan", "prtt_addon.core.io.outdir"), _plan_context),
    Target("exr", "read_sh_exr, read_relight_exr, preview layer sources (in process)", "exr", run_exr, 1 << 16,
           ("prtt_addon.core.io.exr_io", "prtt_addon.core.preview.pack")),
    Target("exr-bands", "preview layer sources' rows (decoded in child processes)", "exr", run_exr_bands, 1 << 16,
           ("prtt_addon.core.io.exr_io", "prtt_addon.core.io.exr_bands", "prtt_addon.core.preview.pack")),
    Target("sidecar", "read_vertex_transfer, read_generated_uvs", "sidecar", run_sidecar, 1 << 14,
           ("prtt_addon.core.io.sidecars",)),
    Target("env", "read_hdr_image (.exr, .hdr RLE) + SH projection", "env", run_env, 1 << 14,
           ("prtt_addon.core.io.image_io", "prtt_addon.core.light.envmap")),
    Target("world", "a World's strength, colour and Mapping rotation -> light", "world", run_world, 256,
           ("prtt_addon.core.light.envmap",)),
    Target("events", "read_event (worker stdout lines)", "events", run_events, 1 << 12, ("prtt_addon.core.base.worker_events",)),
    Target("ktx2", "parse_ktx2", "ktx2", run_ktx2, 1 << 16, ("prtt_addon.core.io.ktx2",)),
    Target("glb", "read_glb_json", "glb", run_glb, 1 << 14, ("prtt_addon.core.io.gltf_prtt",)),
]}


def quick_check(name: str, seeds: list[str]) -> int:
    """Run target ``name`` on its seed files (no fuzzing); returns how many ran."""
    t = TARGETS[name]
    for p in seeds:
        with open(p, "rb") as f:
            t.run(f.read())
    return len(seeds)


