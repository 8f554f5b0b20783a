"""Inter-reflection ("bounce") textures, the paper's section on inter-reflections.

Bounce level k at a texel p is the cosine-weighted incident radiance that
arrives after exactly k reflections, projected to SH:

    B_k(p)_c = integral (1 - V(w)) L_{k-1}(q(w) -> p)_c max(0, n.w) y(w) dw,

stored as ``<set>.bounce<k>.exr`` (channels R.sh000.., G.sh000.., B.sh000..).
At render time it is simply added to the direct incident radiance M(L) T
before the material lobes (shading.shade(..., bounces=...)).

Per texel, rays over the hemisphere (the transfer bake's frames and Sobol'
patterns, balanced weights) are *intersected* with the scene. For a hit q on
a baked surface, the radiance leaving q towards p is the reference shading
model (shading.outgoing) evaluated at q with view direction q -> p, the
material at q, the shading normal at q (normal-mapped where q is), and q's
incident radiance read bilinearly from the textures the renderer will use:
for k = 1 the transfer texture lit by the fixed light (M(L) T_q), for k > 1
the previous bounce texture. It is clamped at 0 (SH ringing).

Skipped work, all counted in the manifest:
* rays that miss are never shaded (their term is exactly 0);
* occluder-only triangles (set -1) have no texture: they absorb (radiance 0);
* texels on the zero-ray analytic path, and texels all of whose *transfer*
  rays escaped (their transfer equals the unoccluded value), get exactly 0
  with no rays. The latter is an approximation: bounce rays are a different
  sample of the hemisphere, so a tiny object that every transfer ray missed
  is missed here too - an error of the size of the transfer's own noise;
* a set whose texels are all skipped is not traced at all and gets no file
  (the renderer treats a missing bounce texture as zero).

Bounce textures bake the light and the materials in (the paper's stated
limitation): the manifest records their hashes so the add-on can flag stale
bounces.
"""
from __future__ import annotations

import dataclasses
import threading
import time

import numpy as np

from .gaunt import tpfl_matrix
from .gbuffer import GBuffer, apply_normal_maps
from .materials import eval_materials
from .parallel import run_chunks
from .raytrace import RayScene
from .rotation import rotate_zyz
from .sampling import pattern_bank
from .shading import outgoing
from .texsample import bilinear
from .transfer import (Cancelled, Points, TransferSettings, _estimator_tables, chunk_frames,
                       pattern_count, unoccluded_transfer)

#: A texel whose float32 transfer is within this of the unoccluded value saw no
#: geometry with any transfer ray (the balanced estimator is exact there; one
#: blocked ray of 4096 moves the DC term by ~2e-4).
OPEN_TOLERANCE = 2e-5
#: The same test on a half-float texture read back from disk (half rounds the
#: coefficients, <= 1.8, by up to 5e-4; one blocked ray of 256 moves the DC
#: term by ~3e-3, of 4096 by ~2e-4, which this then misses).
HALF_OPEN_TOLERANCE = 1.5e-3


@dataclasses.dataclass
class IncidentSet:
    """One set's texture that radiance leaving its surface is computed from."""

    pm: np.ndarray        # (H * W, C) float32, pixel-major
    width: int
    height: int


class HitShader:
    """Radiance leaving hit points towards the ray origins.

    ``incident`` maps set index -> IncidentSet; ``transfer`` says whether its
    textures hold transfer T (K channels, lit by ``light``) or bounce
    radiance (3K channels, R then G then B).
    """

    def __init__(self, sc, incident: dict, light: np.ndarray, bands: int, transfer: bool,
                 normal_maps: bool = True):
        self.sc, self.incident, self.transfer, self.normal_maps = sc, incident, transfer, normal_maps
        self.K = bands * bands
        if transfer:
            # Lp (h, 3K) = T (h, K) @ M2: one float32 matrix product for all hits.
            M = tpfl_matrix(light[:self.K], bands)                     # (3, K, K)
            self.M2 = np.ascontiguousarray(M.reshape(3 * self.K, self.K).T, dtype=np.float32)
        self.params = _TriangleMaterials(sc)

    def radiance(self, tri: np.ndarray, bary: np.ndarray, view: np.ndarray) -> np.ndarray:
        out = np.zeros((tri.size, 3))
        sets = self.sc.set_id[tri]
        for s, inc in self.incident.items():
            sel = np.flatnonzero(sets == s)
            if sel.size == 0:
                continue
            t, b = tri[sel], bary[sel]
            uv = np.einsum("nk,nkc->nc", b, self.sc.uvs[t])
            v = bilinear(inc.pm, inc.width, inc.height, uv)                   # float32
            if self.transfer:
                Lp = (v @ self.M2).reshape(sel.size, 3, self.K)
            else:
                Lp = v.reshape(sel.size, 3, self.K)
            n = np.einsum("nk,nkc->nc", b, self.sc.normals[t].astype(np.float64))
            n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
            if self.normal_maps:
                n, _ = apply_normal_maps(self.sc, t, b, n)
            out[sel] = outgoing(Lp, n, view[sel], self.params.at(t, b))
        return out


class _TriangleMaterials:
    """Shading parameters of every triangle's material, looked up per hit;
    only textured materials are evaluated at the hit point itself."""

    def __init__(self, sc):
        self.sc = sc
        T = sc.n_triangles
        centre = np.full((T, 3), 1.0 / 3.0)
        p = eval_materials(sc, np.arange(T), centre)
        self.albedo, self.spec, self.exponent = p.albedo, p.spec, p.exponent
        from .materials import Material
        mats = [Material.from_dict(m) for m in sc.materials]
        mid = sc.material_id if sc.material_id is not None else np.full(T, -1)
        textured_ids = [i for i, m in enumerate(mats) if m.textured]
        self.textured = np.isin(mid, textured_ids) if textured_ids else np.zeros(T, bool)

    def at(self, tri, bary):
        from .materials import ShadingParams
        p = ShadingParams(self.albedo[tri], self.spec[tri], self.exponent[tri])
        tx = np.flatnonzero(self.textured[tri])
        if tx.size:
            q = eval_materials(self.sc, tri[tx], bary[tx])
            p.albedo[tx], p.spec[tx], p.exponent[tx] = q.albedo, q.spec, q.exponent
        return p


def open_texels(T_texels: np.ndarray, normals: np.ndarray, bands: int,
                tol: float = OPEN_TOLERANCE) -> np.ndarray:
    """(N,) bool: transfer equals the unoccluded clamped cosine (no ray blocked)."""
    A = unoccluded_transfer(normals, bands)
    return np.abs(T_texels.astype(np.float64) - A).max(axis=1) <= tol


def bake_bounce_set(rs: RayScene, gb: GBuffer, pts: Points, skip: np.ndarray, shader: HitShader,
                    st: TransferSettings, level: int, *, progress=None, cancel=None):
    """One set's bounce level: returns ((3K, H*W) float32 texture, coverage mask
    (H, W), stats). ``skip`` (N,) marks texels that get zero without rays."""
    K = st.bands ** 2
    tex = np.zeros((3 * K, gb.height * gb.width), np.float32)
    todo = np.flatnonzero(~skip)
    stats = {"texels": int(gb.n), "skipped_texels": int(skip.sum()), "rays_traced": 0,
             "hits_shaded": 0}
    lock = threading.Lock()
    # Each level gets its own patterns (ids tagged with the level).
    ids = pts.ids + (np.int64(level) << 50)
    sub = Points(pts.position[todo], pts.normal[todo], pts.geo_normal[todo], ids[todo],
                 np.zeros(todo.size, bool), None)
    G = pattern_count(st)
    dirs_bank, _, _ = pattern_bank(G, st.rays, st.bands, st.sampler, st.distribution, st.seed)
    _, table = _estimator_tables(st, G, st.rays)
    from .sampling import hash_u32
    pattern = (hash_u32(st.seed, sub.ids, 0x9A77) % np.uint32(G)).astype(np.int64)
    order = np.argsort(pattern, kind="stable")
    per_chunk = max(1, st.chunk_rays // st.rays)
    chunks = []
    for g in range(G):
        sel = order[pattern[order] == g]
        for a in range(0, sel.size, per_chunk):
            chunks.append((g, sel[a:a + per_chunk]))

    def run(chunk):
        g, idx = chunk
        if cancel is not None and cancel.is_set():
            raise Cancelled()
        fr = chunk_frames(rs, sub, idx, st.seed)
        n, S = idx.size, st.rays
        D = np.matmul(dirs_bank[g][None], fr.R.transpose(0, 2, 1)).reshape(-1, 3)
        O = np.repeat(fr.origins, S, axis=0)
        prim, u, v, _ = rs.intersect(O, np.ascontiguousarray(D))
        hit = np.flatnonzero(prim >= 0)
        L = np.zeros((n * S, 3), np.float32)
        if hit.size:
            bary = np.stack([1.0 - u[hit] - v[hit], u[hit], v[hit]], axis=1).astype(np.float64)
            L[hit] = shader.radiance(prim[hit].astype(np.int64), bary, -D[hit].astype(np.float64))
        L = L.reshape(n, S, 3)
        local = np.stack([L[:, :, c] @ table[g] for c in range(3)], axis=1)     # (n, 3, K)
        rep = lambda a: np.repeat(a, 3)  # noqa: E731
        world = rotate_zyz(local.reshape(n * 3, K), rep(fr.alpha), rep(fr.beta), rep(fr.gamma))
        tex[:, gb.texel[todo[idx]]] = world.reshape(n, 3 * K).T
        with lock:
            stats["rays_traced"] += n * S
            stats["hits_shaded"] += int(hit.size)
        return n

    t0 = time.perf_counter()
    done = 0

    def on_result(n):
        nonlocal done
        done += n
        if progress:
            progress(done, todo.size, stats["rays_traced"])

    run_chunks(run, chunks, st.n_threads, on_result, cancel)
    stats["seconds"] = time.perf_counter() - t0
    mask = np.zeros(gb.height * gb.width, bool)
    mask[gb.texel] = True
    return tex, mask.reshape(gb.height, gb.width), stats


def bounce_settings(st: TransferSettings, bounce_rays: int) -> TransferSettings:
    """The transfer settings a bounce pass traces with (its own ray count)."""
    return dataclasses.replace(st, rays=bounce_rays, adaptive_tol=0.0, analytic=False,
                               estimator="balanced")

