"""The bake's first stage: what its inputs are, what of the folder it may reuse,
whether it fits in memory.

Work the inputs do not need is skipped: an identical bake is not repeated,
and when only the light or the materials changed, only the bounce textures
are re-baked (from the transfer textures on disk). "Identical" is checked on
the files themselves: the manifest records each output's size and sha256
(``file_info``), and a missing, truncated or replaced output is re-baked.
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
import os

import numpy as np

from ...base.errors import BakeError
from ...base.memory import check_fits, resident_bytes
from ...io.outdir import verify_files
from ...model.scene import geometry_hash
from ...shading.materials import materials_hash
from ...shading.shade import light_hash
from ..estimators import denoise, hit_kernel
from ..estimators.relightable import GLOSSY_BANDS, relight_shared_colour
from .context import MANIFEST, BakeContext, BakeSettings, asked_downscale
from .memory_plan import covered_texels, peak_stage, process_extra, stage_bytes, uv_areas, uv_boundaries


def settings_hash(settings: BakeSettings) -> str:
    """sha256 hex of the settings that change the transfer textures (BakeSettings.result_key)."""
    return hashlib.sha256(json.dumps(settings.result_key(), sort_keys=True).encode()).hexdigest()


def read_manifest(out_dir) -> dict | None:
    """The folder's manifest as a dict, or None (missing, unreadable, not an object)."""
    try:
        with open(os.path.join(out_dir, MANIFEST), encoding="utf-8") as f:
            m = json.load(f)
    except (OSError, ValueError, RecursionError):
        return None
    return m if isinstance(m, dict) else None


def manifest_dicts(x) -> list:
    """The dict entries of a manifest list (anything else in it is ignored)."""
    return [d for d in x if isinstance(d, dict)] if isinstance(x, list) else []


def plain_names(names) -> bool:
    """A list of bare file names (a manifest is read from disk: no paths out of the folder)."""
    return isinstance(names, list) and all(
        isinstance(n, str) and n and os.path.basename(n) == n and not n.startswith(".") for n in names)


def outputs_changed(m: dict, out_dir, files) -> str | None:
    """Why ``files`` in ``out_dir`` are not the ones manifest ``m`` recorded (a
    file missing, of another size or content, or a manifest without file_info),
    or None when every one checks out (size and sha256)."""
    if not plain_names(files):
        return "the manifest's file list is not a list of file names"
    return verify_files(out_dir, files, m.get("file_info"))


def bounce_key(in_hash: str, set_hash: str, light: np.ndarray | None, mat_hash: str,
               st: BakeSettings) -> str:
    """Identity of the bounce textures: transfer, light (not for relightable
    bounces, which do not depend on it), materials, bounce settings."""
    relightable = st.bounce_mode == "relightable"
    if relightable:
        light = None
    h = hashlib.sha256("|".join([in_hash, set_hash, light_hash(light) if light is not None else "-",
                                 mat_hash, str(st.bounces), str(st.bounce_rays),
                                 repr(float(st.bounce_tolerance)), st.bounce_denoise]
                                + ([f"downscale={st.bounce_downscale}"] if st.bounce_downscale != 1 else [])
                                + ([f"tuning={st.tuning}"] if st.tuning != "fixed" else [])
                                + (["mode=relightable"] if relightable else [])).encode())
    return h.hexdigest()


def bake_stage_bytes(set_sizes, st: BakeSettings, *, n_triangles: int, bouncing: bool,
                     downscales: list[int] | None = None, compiling: bool = False,
                     extra: int = 0, dask: bool = False) -> dict[str, int]:
    """Estimated peak bytes of each stage of a bake (memory_plan.stage_bytes).
    ``set_sizes``: (width, height, covered texels) per set baked, in order
    (covered: memory_plan.covered_texels of the set's UV area); ``downscales``:
    each set's bounce grid once chosen (default: the grid the settings ask for);
    ``compiling``: the bounce's kernels are compiled in this process (:func:`kernels_compile`);
    ``extra``: what the process holds beyond a bare worker (memory_plan.process_extra);
    ``dask``: the rays are traced on a Dask cluster (this process is its client)."""
    K = st.bands ** 2
    kg = min(GLOSSY_BANDS, st.bands) ** 2
    colours = 1 if relight_shared_colour(st) else 3
    return stage_bytes([tuple(int(v) for v in s) for s in set_sizes], bands=st.bands, dilate=st.dilate,
                       n_triangles=n_triangles, threads=st.n_threads, chunk_rays=st.chunk_rays, mips=st.mips,
                       rays=st.rays, bounce_rays=st.bounce_rays,
                       bounces=st.bounces if bouncing else 0, bounce_mode=st.bounce_mode,
                       downscale=(downscales if downscales is not None
                                  else asked_downscale(st.bounces, st.tuning, st.bounce_downscale)),
                       relight_channels=3 * K + colours * (kg - 1) * kg, glossy_coeffs=kg * kg,
                       compiling=compiling, extra=extra, dask=dask)


def job_array_bytes(scene) -> int:
    """Bytes of the scene's numpy arrays (what the loaded job holds)."""
    return sum(a.nbytes for a in vars(scene).values() if isinstance(a, np.ndarray))


def kernels_compile(ctx: BakeContext, plan: BakePlan) -> bool:
    """This bake's process will compile the bounce's numba kernels (runner's
    hit_kernel.warm_up finds them missing from numba's cache): a local bake with bounces."""
    st = ctx.settings
    return (plan.bouncing and ctx.dask is None
            and hit_kernel.compile_pending(st.bands, relightable=st.bounce_mode == "relightable",
                                           glossy_bands=min(GLOSSY_BANDS, st.bands)))


def bake_memory_bytes(set_sizes, st: BakeSettings, *, n_triangles: int, bouncing: bool) -> int:
    """The largest of :func:`bake_stage_bytes`: the bake's estimated peak."""
    return peak_stage(bake_stage_bytes(set_sizes, st, n_triangles=n_triangles, bouncing=bouncing))[1]


def scene_set_sizes(sc, set_ids) -> list[tuple[int, int, int]]:
    """(width, height, covered texels estimated from the UV area) of sets ``set_ids`` of ``sc``."""
    areas = uv_areas(sc.uvs, sc.set_id, sc.n_sets)
    edges = uv_boundaries(sc.uvs, sc.set_id, sc.n_sets)
    out = []
    for s in set_ids:
        w, h = (int(v) for v in sc.set_resolution[s])
        out.append((w, h, covered_texels(float(areas[s]), w, h, float(edges[s]))))
    return out


@dataclasses.dataclass(frozen=True, eq=False)
class BakePlan:
    """What a bake will do (plan_bake): its input hashes and reuse decisions.

    Hashes are sha256 hex digests. A distributed runner computes this once and
    hands it to every stage that writes files (their attributes name the inputs).
    """

    input_hash: str              # scene.geometry_hash: every array that changes the transfer
    settings_hash: str           # settings_hash(settings)
    light_hash: str | None       # shading.shade.light_hash of the prepared light; None without a light
    materials_hash: str          # shading.materials.materials_hash(scene)
    bouncing: bool               # bounce levels will be baked (bounces > 0, textures on, a light given)
    bounce_key: str | None       # bounce_key(...) when bouncing, else None
    old_manifest: dict | None    # the folder's manifest before this bake (read_manifest)
    transfer_reused: bool        # the transfer outputs on disk are this bake's: read, not traced
    bounce_reused: bool          # the bounce outputs on disk are this bake's (or none are wanted nor there)

    @property
    def skipped(self) -> bool:
        """Nothing to bake: every output on disk is this bake's."""
        return self.transfer_reused and self.bounce_reused

    def exr_attrs(self, st: BakeSettings) -> dict:
        """Header attributes every texture of this bake carries (stages add their own)."""
        return {"rays": st.rays, "seed": st.seed, "sampler": st.sampler,
                "estimator": st.estimator, "input_hash": self.input_hash}


def plan_bake(ctx: BakeContext, *, skip_if_unchanged: bool = True) -> BakePlan:
    """Hash the inputs and decide what the folder's outputs let this bake reuse.

    Warns when bounces are asked for without a light (they are skipped) and
    when recorded outputs no longer match their manifest (re-baked); raises
    BakeError when the oidn denoiser is asked for but pyoidn is missing.
    ``skip_if_unchanged`` False: reuse nothing.
    """
    sc, st = ctx.scene, ctx.settings
    in_hash = geometry_hash(sc)
    set_hash = settings_hash(st)
    bouncing = st.bounces > 0 and st.textures
    if bouncing and ctx.light is None and st.bounce_mode != "relightable":
        ctx.warn("no light given: bounce textures (which bake the light in) are skipped")
        bouncing = False
    if bouncing and st.bounce_mode == "relightable" and denoise.resolve_filter(st.bounce_denoise,
                                                                            st.bounce_rays) != "none":
        raise BakeError("bounce denoising is not available for relightable bounces (bounce_mode relightable); "
                        "use --bounce-denoise none or --bounce-mode baked")
    if bouncing and st.bounce_denoise == "oidn" and not denoise.oidn_available():
        raise BakeError("bounce denoiser 'oidn' needs the optional package pyoidn (pip install pyoidn); "
                        "or use --bounce-denoise edge-aware or none")
    l_hash = light_hash(ctx.light) if ctx.light is not None else None
    m_hash = materials_hash(sc)
    b_key = bounce_key(in_hash, set_hash, ctx.light, m_hash, st) if bouncing else None
    old = read_manifest(ctx.out_dir)
    transfer_ok, bounce_ok = reusable(ctx, old, in_hash, set_hash, b_key, bouncing=bouncing,
                                      skip_if_unchanged=skip_if_unchanged)
    return BakePlan(input_hash=in_hash, settings_hash=set_hash, light_hash=l_hash, materials_hash=m_hash,
                    bouncing=bouncing, bounce_key=b_key, old_manifest=old,
                    transfer_reused=transfer_ok, bounce_reused=bounce_ok)


def reusable(ctx: BakeContext, old: dict | None, in_hash: str, set_hash: str, b_key: str | None, *,
             bouncing: bool, skip_if_unchanged: bool) -> tuple[bool, bool]:
    """(transfer outputs reusable, bounce outputs reusable) per the old manifest,
    with every file checked against its recorded size and sha256. A mismatch is
    reported as a warning and that part is re-baked."""
    if not (skip_if_unchanged and old):
        return False, False
    same_inputs = old.get("input_hash") == in_hash and old.get("settings_hash") == set_hash
    transfer_ok = False
    if same_inputs:
        why = outputs_changed(old, ctx.out_dir, old.get("transfer_files", old.get("files", [])))
        transfer_ok = why is None
        if why:
            ctx.warn(f"re-baking the transfer: {why}")
    old_bounce = old.get("bounce") or {}
    if not bouncing:
        return transfer_ok, not old_bounce.get("files")
    if old_bounce.get("key") != b_key:
        return transfer_ok, False
    why = outputs_changed(old, ctx.out_dir, old_bounce.get("files", []))
    if why:
        ctx.warn(f"re-baking the bounce textures: {why}")
    return transfer_ok, why is None


def check_memory(ctx: BakeContext, plan: BakePlan, downscales: list[int] | None = None) -> None:
    """MemoryLimitError unless the bake's estimated peak (:func:`bake_stage_bytes`:
    the largest stage) fits in the memory available, before anything of the
    bake is allocated; the estimate goes into the manifest's ``memory``. The
    refusal names the estimate, the memory available and what to lower.

    Called again with ``downscales`` once the first G-buffer has chosen the
    bounce grids (a grid that cannot be coarser, thin UV margins at this
    resolution, holds 4x the bounce texels): before the trace allocates."""
    sc, st = ctx.scene, ctx.settings
    first = ctx.memory.held_extra is None
    before = resident_bytes() if first else None
    compiling = kernels_compile(ctx, plan)        # imports numba for a bake with bounces
    if first:
        # Read once, before the bake allocates: what the process holds, and what
        # numba's import took (both vary with the machine: file-backed pages).
        ctx.memory.held_extra = process_extra(before, job_array_bytes(sc), resident_bytes())
    sizes = scene_set_sizes(sc, ctx.set_ids) if st.textures else []
    stages = bake_stage_bytes(sizes, st, n_triangles=sc.n_triangles, bouncing=plan.bouncing,
                              downscales=downscales, compiling=compiling, extra=ctx.memory.held_extra,
                              dask=ctx.dask is not None)
    stage, need = peak_stage(stages)
    ctx.memory.estimate_mb = round(need / 2 ** 20, 1)
    biggest = max(sizes, key=lambda s: s[0] * s[1], default=None)
    what = (f"the bake ({len(sizes)} texture set(s), the largest {biggest[0]}x{biggest[1]}, {st.bands} bands"
            + (f", {st.bounces} {st.bounce_mode} bounce(s)" if plan.bouncing else "") + f"; its peak: {stage})"
            if biggest else "the bake")
    check_fits(need, what, advice="lower --resolution (memory grows with texels), --bands, or the bounces "
                                   "(--bounces, --bounce-downscale 2 or 4), or give the objects smaller "
                                   "texture sets")
