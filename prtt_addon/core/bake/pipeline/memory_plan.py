"""What a bake will hold in memory, estimated before it starts (plan.py
checks the sum against the memory available, base/memory.check_fits)."""
from __future__ import annotations

from ..estimators.transfer import SHARED_FACTOR


def set_bytes(width: int, height: int, n_coeffs: int, *, rgb: bool = False,
              threads: int = 2, chunk_rays: int = 1 << 19, rays: int = 256,
              bounce: bool = False) -> int:
    """Peak bytes for baking one texture set (measured structure, rounded up):

    * the float32 texture and the kernels' texel rows (or the dilation's copy):
      2 x W H K' x 4 (K' = 3K for RGB);
    * the G-buffer, <= W H texels x ~160 B (positions, normals, ids, barycentrics);
    * rasteriser temporaries, bounded by its chunk: ~200 MB per G-buffer row
      band, max(2, threads) bands built at once;
    * per thread: rays of one chunk x ~64 B (origins, directions, results) plus
      the chunk's occlusion bits (texels x rays bytes), or a shared-frame chunk
      (transfer.SHARED_FACTOR x as many rays, 9 B each), whichever is larger;
    * with bounces, what stays resident for every set until the last level:
      see :func:`bounce_resident_bytes`.
    """
    k = n_coeffs * (3 if rgb else 1)
    texels = width * height
    return (2 * texels * k * 4 + texels * 160 + max(2, threads) * 200 * 1024 ** 2
            + threads * chunk_rays * max(64 + 2, 9 * SHARED_FACTOR)
            + (bounce_resident_bytes(width, height, n_coeffs) if bounce else 0))


def bvh_bytes(n_triangles: int) -> int:
    """Embree's scene for ``n_triangles``: its vertex and index buffers and the BVH,
    measured 243 MB for 2M triangles (robust build), plus the float32 copy of
    one build chunk: ~128 B a triangle."""
    return 128 * int(n_triangles)


def bounce_resident_bytes(width: int, height: int, n_coeffs: int) -> int:
    """Bytes a set keeps in memory during bounce levels, per texel: its incident
    radiance at the valid texels (3K floats), its exit rows (3 + 6 + 3K floats,
    read by every set's rays), the level being baked (3K floats), its surface
    texels (10 doubles) and its G-buffer (~140 B): 4 (9K + 9) + 220."""
    return width * height * (4 * (9 * n_coeffs + 9) + 220)


def relight_resident_bytes(width: int, height: int, n_coeffs: int, glossy_coeffs: int,
                           glossy_colours: int = 3) -> int:
    """bounce_resident_bytes for relightable bounces (relightable_stage.py): per
    texel C = 3K + g (Kg - 1) Kg floats of stored operator (g = glossy_colours:
    3, or 1 for glossy rows shared between colours), held twice (the sum over
    levels, the level being baked), and C3 (g = 3) twice more (the next
    level's rows, tinted per colour, and exit rows of at most C3 + 6 floats),
    surface texels and G-buffer: 4 (2 C + 2 C3 + 6) + 220."""
    glossy = (glossy_coeffs - 1) * glossy_coeffs
    C, C3 = 3 * n_coeffs + glossy_colours * glossy, 3 * n_coeffs + 3 * glossy
    return width * height * (4 * (2 * C + 2 * C3 + 6) + 220)
