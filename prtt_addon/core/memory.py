"""Memory estimates, checked before a bake allocates anything.

A request that cannot fit gets a clear error naming the set and the numbers,
instead of the kernel's OOM killer taking the worker (and its partial work).
"""
from __future__ import annotations

import os

GiB = 1024 ** 3


class MemoryLimitError(RuntimeError):
    """The bake would need more memory than is available."""


def available_bytes() -> int | None:
    """MemAvailable from /proc/meminfo (Linux), else physical pages, else None."""
    try:
        with open("/proc/meminfo", encoding="ascii") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        return None


def set_bytes(width: int, height: int, n_coeffs: int, *, rgb: bool = False,
              threads: int = 2, chunk_rays: int = 1 << 19, rays: int = 256,
              bounce: bool = False) -> int:
    """Peak bytes for baking one texture set (measured structure, rounded up):

    * the float32 texture and its dilated copy: 2 x W H K' x 4 (K' = 3K for RGB);
    * the G-buffer, <= W H texels x ~160 B (positions, normals, ids, barycentrics);
    * rasteriser temporaries, bounded by its chunk: ~200 MB;
    * per thread: rays of one chunk x ~64 B (origins, directions, results) plus
      the chunk's occlusion bits (texels x rays bytes);
    * with bounces, what stays resident for every set until the last level:
      see :func:`bounce_resident_bytes`.
    """
    k = n_coeffs * (3 if rgb else 1)
    texels = width * height
    return (2 * texels * k * 4 + texels * 160 + 200 * 1024 ** 2
            + threads * (chunk_rays * 64 + chunk_rays * 2)
            + (bounce_resident_bytes(width, height, n_coeffs) if bounce else 0))


def bounce_resident_bytes(width: int, height: int, n_coeffs: int) -> int:
    """Bytes a set keeps in memory during bounce levels: its transfer (K floats a
    texel, read by every other set's rays), two RGB bounce levels (3K each) and
    its G-buffer: 4 (K + 6K) + 160 per texel."""
    return width * height * (4 * 7 * n_coeffs + 160)


def check_fits(needed: int, what: str, *, fraction: float = 0.8) -> None:
    """Raise MemoryLimitError if ``needed`` exceeds ``fraction`` of available memory."""
    avail = available_bytes()
    if avail is not None and needed > fraction * avail:
        raise MemoryLimitError(
            f"{what} needs about {needed / GiB:.1f} GiB but only {avail / GiB:.1f} GiB is "
            f"available; lower the resolution or the bands, or bake fewer sets at once")
