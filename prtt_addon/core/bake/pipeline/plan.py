"""The bake's first stage: what its inputs are and what of the folder it may
reuse (whether it fits in memory: memory_check.py).

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
from ...io.outdir import verify_files
from ...model.scene import geometry_hash
from ...shading.materials import materials_hash
from ...shading.shade import light_hash
from ..estimators import denoise
from .context import MANIFEST, BakeContext, BakeSettings
from .sun_stage import sun_key


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
    sun_key: str | None = None   # sun_stage.sun_key: the sun masks' key; None without a sun
    sun_reused: bool = True      # the sun masks on disk (or their absence) are this bake's

    @property
    def skipped(self) -> bool:
        """Nothing to bake: every output on disk is this bake's."""
        return self.transfer_reused and self.bounce_reused and self.sun_reused

    @property
    def sun_only(self) -> bool:
        """The transfer on disk is reused, the sun's masks are baked (or removed) anew."""
        return self.transfer_reused and not self.sun_reused

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
    b_key = bounce_key(in_hash, set_hash, ctx.bounce_light, m_hash, st) if bouncing else None
    old = read_manifest(ctx.out_dir)
    s_key = sun_key(ctx.sun, in_hash, st.sun_detail, st.sun_refine, st.sun_edges, ctx.lamps)
    transfer_ok, bounce_ok, sun_ok = reusable(ctx, old, in_hash, set_hash, b_key, bouncing=bouncing,
                                              skip_if_unchanged=skip_if_unchanged, sun=s_key)
    return BakePlan(input_hash=in_hash, settings_hash=set_hash, light_hash=l_hash, materials_hash=m_hash,
                    bouncing=bouncing, bounce_key=b_key, old_manifest=old,
                    transfer_reused=transfer_ok, bounce_reused=bounce_ok, sun_key=s_key, sun_reused=sun_ok)


def reusable(ctx: BakeContext, old: dict | None, in_hash: str, set_hash: str, b_key: str | None, *,
             bouncing: bool, skip_if_unchanged: bool, sun: str | None = None) -> tuple[bool, bool, bool]:
    """(transfer outputs reusable, bounce outputs reusable, sun masks reusable)
    per the old manifest, with every file checked against its recorded size
    and sha256. A mismatch is reported as a warning and that part is
    re-baked. ``sun``: the sun masks' key (sun_stage.sun_key, None without a
    sun), which the old manifest's "sun" must match; a sun turned, come or
    gone bakes the masks alone (stages.sun_only_set) over the reused transfer."""
    if not (skip_if_unchanged and old):
        return False, False, False
    # The masks' key is the sun's entry's, or without a sun the lamps' entry's.
    old_sun = next((old[k] for k in ("sun", "lamps") if isinstance(old.get(k), dict)), {})
    same_inputs = old.get("input_hash") == in_hash and old.get("settings_hash") == set_hash
    transfer_ok = False
    if same_inputs:
        why = outputs_changed(old, ctx.out_dir, old.get("transfer_files", old.get("files", [])))
        transfer_ok = why is None
        if why:
            ctx.warn(f"re-baking the transfer: {why}")
    sun_ok = transfer_ok and old_sun.get("key") == sun
    old_bounce = old.get("bounce") or {}
    if not bouncing:
        return transfer_ok, not old_bounce.get("files"), sun_ok
    if old_bounce.get("key") != b_key:
        return transfer_ok, False, sun_ok
    why = outputs_changed(old, ctx.out_dir, old_bounce.get("files", []))
    if why:
        ctx.warn(f"re-baking the bounce textures: {why}")
    return transfer_ok, why is None, sun_ok


