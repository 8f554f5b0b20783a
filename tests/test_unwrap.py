"""xatlas unwrapping (in a child process: crashes and hangs retried) and scene assembly."""
import numpy as np
import pytest

from prtt_addon.core.texels.raster import rasterize
from prtt_addon.core.texels.unwrap import UnwrapError, unwrap
from prtt_addon.dev.bench import meshgen as mg


def test_unwrap_fits_inside_without_overlaps():
    meshes = [mg.uv_sphere(1.0, 24, 12), mg.torus(1.0, 0.3, 24, 12), mg.box((1, 2, 3))]
    uvs = unwrap([(m.vertices, m.faces) for m in meshes], 256, padding=2)
    for m, uv in zip(meshes, uvs):
        assert uv.shape == (m.n_faces, 3, 2)
        assert uv.min() >= 0 and uv.max() <= 1
    r = rasterize(np.concatenate(uvs), 256, 256)
    assert r.overlap_texels == 0


def test_unwrap_keeps_face_order():
    """Each UV triangle's 3D/2D area ratio is about constant (one texel density),
    which only holds if UV triangle k belongs to face k."""
    m = mg.uv_sphere(1.0, 32, 16)
    uv = unwrap([(m.vertices, m.faces)], 512)[0]
    P = m.corner_positions()
    a3 = 0.5 * np.linalg.norm(np.cross(P[:, 1] - P[:, 0], P[:, 2] - P[:, 0]), axis=1)
    d = uv[:, 1] - uv[:, 0], uv[:, 2] - uv[:, 0]
    a2 = 0.5 * np.abs(d[0][:, 0] * d[1][:, 1] - d[0][:, 1] * d[1][:, 0])
    ok = a3 > 1e-6
    ratio = a2[ok] / a3[ok]
    assert np.median(np.abs(ratio / np.median(ratio) - 1)) < 0.3


def test_unwrap_errors():
    with pytest.raises(UnwrapError, match="without faces"):
        unwrap([(np.zeros((3, 3)), np.zeros((0, 3), int))], 64)
    with pytest.raises(ValueError, match="resolution must be >= 8"):
        unwrap([(mg.box().vertices, mg.box().faces)], 4)


def test_assemble_sets_and_obj_loading():
    spot = mg.load_obj(mg.asset_path("spot.obj"))
    assert spot.n_faces == 5856 and spot.uvs is not None and spot.normals is not None
    # spot's own UVs reach -0.052 .. 1.0007: refused with a clear message ...
    from prtt_addon.core.model.scene import SceneError
    with pytest.raises(SceneError, match="10 triangles of set.* spot have UVs outside"):
        mg.assemble([("spot", spot)], resolution=128, keep_uvs=True)
    # ... and fine once re-unwrapped.
    sc = mg.assemble([("spot", spot), ("box", mg.box())], resolution=128)
    assert sc.set_names == ["spot", "box"] and sc.n_triangles == 5856 + 12


def _flaky_python(tmp_path, first_run: str) -> str:
    """An interpreter whose first start does ``first_run`` (shell) instead of
    running Python: what a crashing or hanging xatlas child looks like."""
    import sys
    marker = tmp_path / "started-once"
    script = tmp_path / "flaky-python"
    script.write_text(f"#!/bin/sh\nif [ ! -e '{marker}' ]; then touch '{marker}'; {first_run}; fi\n"
                      f"exec '{sys.executable}' \"$@\"\n")
    script.chmod(0o755)
    return str(script)


@pytest.mark.parametrize("first_run", ["kill -SEGV $$", "exec sleep 600"], ids=["crash", "hang"])
def test_a_crashed_or_hung_xatlas_child_is_started_again(tmp_path, monkeypatch, first_run):
    from prtt_addon.core.texels import unwrap as uw
    monkeypatch.setattr(uw, "python_executable", lambda: _flaky_python(tmp_path, first_run))
    monkeypatch.setattr(uw, "_child_timeout", lambda meshes: 5.0)
    m = mg.uv_sphere(1.0, 16, 8)
    uv = uw.unwrap([(m.vertices, m.faces)], 64)[0]
    assert (tmp_path / "started-once").exists()             # the first child did fail
    assert uv.shape == (len(m.faces), 3, 2) and np.all((uv >= 0) & (uv <= 1))


def test_an_xatlas_child_that_always_fails_is_reported(tmp_path, monkeypatch):
    from prtt_addon.core.texels import unwrap as uw
    monkeypatch.setattr(uw, "python_executable", lambda: "/bin/false")
    m = mg.uv_sphere(1.0, 16, 8)
    with pytest.raises(uw.UnwrapError, match="failed 3 times"):
        uw.unwrap([(m.vertices, m.faces)], 64)
