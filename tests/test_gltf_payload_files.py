"""The glTF export's payloads made from the bake's files a band of rows at a
time (core/io/gltf_prtt.file_payloads, bounce_files_payload) are the bytes
the array payloads make of what exr_io reads (issue 50: a 2048² relightable
set's export held the whole texture as float32 several times over, 21.6 GB),
and what they hold is within gltf_prtt.set_payload_bytes, the bound the
export checks before it reads a file."""
import tracemalloc

import numpy as np
import pytest

from prtt_addon.core.io import exr_io
from prtt_addon.core.io import gltf_prtt as gp

K = 9


def _planes(rng, n, h, w):
    return (rng.standard_normal((n, h, w)) * rng.uniform(0.01, 3.0, (n, 1, 1))).astype(np.float32)


def _relight(path, rng, h, w, *, shared, half, kg=4):
    names = exr_io.relight_channel_names(K, kg, shared)
    attrs = {"glossy_bands": int(round(kg ** 0.5))}
    if shared:
        attrs["glossy_colour"] = "shared"
    exr_io.write_sh_planes(path, _planes(rng, len(names), h, w), kind="relight", half=half, names=names,
                           bands=3, attrs=attrs)
    return path


@pytest.mark.parametrize("encoding", ["half", "u8"])
@pytest.mark.parametrize("half", [True, False])
def test_file_payloads_are_the_array_payloads_bytes(tmp_path, encoding, half):
    rng = np.random.default_rng(5 + half)
    h, w = 37, 52
    t = str(tmp_path / "a.transfer.exr")
    exr_io.write_sh_planes(t, _planes(rng, K, h, w), kind="transfer", half=half)
    data, _ = exr_io.read_sh_exr(t)
    want = gp.transfer_payload(np.ascontiguousarray(data[::-1].transpose(2, 0, 1)), encoding=encoding)
    assert gp.file_payloads(t, encoding) == {"transfer": want}
    for shared, kg in ((False, 4), (True, 9), (False, 0)):
        r = _relight(str(tmp_path / f"r{shared}{kg}.relight.exr"), rng, h, w, shared=shared, half=half, kg=kg)
        dc, glossy, _ = exr_io.read_relight_exr(r, expand=False)
        want = {"relightDC": gp.relight_dc_payload(np.ascontiguousarray(dc[::-1].transpose(2, 3, 0, 1)),
                                                   encoding=encoding)}
        if kg:
            axes = (2, 3, 4, 0, 1) if glossy.ndim == 5 else (2, 3, 0, 1)
            want["relightGlossy"] = gp.relight_glossy_payload(np.ascontiguousarray(glossy[::-1].transpose(*axes)),
                                                              K, encoding=encoding)
        assert gp.file_payloads(r, encoding) == want, (shared, kg)


@pytest.mark.parametrize("encoding", ["half", "u8"])
def test_bounce_levels_summed_from_files_are_load_bounce_s(tmp_path, encoding):
    """Baked bounce levels, the second band-limited (4 of 9 coefficients,
    padded with zeros as PreviewSet.load_bounce pads it), summed in order;
    a level that holds other coefficients is reported, not exported."""
    rng = np.random.default_rng(11)
    h, w = 33, 20
    paths, levels = [], []
    for i, (k, attrs) in enumerate(((K, {}), (4, {"band_limited": 1}))):
        p = str(tmp_path / f"s.bounce{i + 1}.exr")
        exr_io.write_sh_planes(p, _planes(rng, 3 * k, h, w), kind="bounce", rgb=True, attrs=attrs)
        b, _ = exr_io.read_sh_exr(p)
        if k < K:
            b = np.concatenate([b, np.zeros(b.shape[:-1] + (K - k,), b.dtype)], axis=-1)
        paths.append(p)
        levels.append(b)
    total = levels[0] + levels[1]
    want = gp.bounce_payload(np.ascontiguousarray(total[::-1].transpose(2, 3, 0, 1)), 2, encoding=encoding)
    assert gp.bounce_files_payload(paths, K, encoding) == want
    assert gp.bounce_files_payload(paths[1:], K, encoding) != want
    assert gp.bounce_files_payload(paths[:1], 16, encoding) == K          # holds 9, the bake 16: left out


@pytest.mark.parametrize("encoding", ["half", "u8"])
def test_what_a_set_s_payloads_hold_is_within_the_checked_bound(tmp_path, encoding):
    """tracemalloc (numpy's arrays and the compressed bytes) over making a
    256² relightable set's payloads, against set_payload_bytes: within it,
    and more than half of it (a bound that says something)."""
    rng = np.random.default_rng(3)
    t = str(tmp_path / "a.transfer.exr")
    exr_io.write_sh_planes(t, _planes(rng, K, 256, 256), kind="transfer")
    r = _relight(str(tmp_path / "a.relight.exr"), rng, 256, 256, shared=False, half=True, kg=9)
    bound = gp.set_payload_bytes(t, r, [], K, encoding)
    tracemalloc.start()
    try:
        made = {**gp.file_payloads(t, encoding), **gp.file_payloads(r, encoding)}
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert set(made) == {"transfer", "relightDC", "relightGlossy"}
    print(f"{encoding}: peak {peak / 2 ** 20:.1f} MiB of a bound of {bound / 2 ** 20:.1f} MiB")
    assert 0.5 * bound < peak <= bound, (peak, bound)
