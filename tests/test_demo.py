"""The README's main job, at a small size: every stage runs and says where its output is."""
import os
import re
import subprocess
import sys

import numpy as np
import pytest

pytestmark = pytest.mark.blender
ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def test_demo_runs_end_to_end(tmp_path):
    pytest.importorskip("bpy")
    out = tmp_path / "demo"
    r = subprocess.run([sys.executable, "-m", "prtt_addon.dev.demo", "--out", str(out), "--resolution", "128",
                        "--rays", "32", "--bounce-rays", "8", "--size", "160x90"],
                       capture_output=True, text=True, timeout=900, cwd=str(tmp_path),
                       env=dict(os.environ, PYTHONPATH=ROOT))
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    for step in ("[1/5] built the room-class scene: 14 objects, 21024 triangles",
                 "[2/5] unwrapped", "[3/5] baked transfer", "1 bounce", "[4/5] rendered 160x90",
                 "[5/5] relightable bounces", "side by side:", "relit at 90", "stage times:"):
        assert step in r.stdout, (step, r.stdout)
    for f in ("demo_side_by_side.png", "demo_tpfl.png", "demo_vertex-tpfl.png", "prtt_demo.blend",
              "textures/atlas.transfer.exr", "textures/atlas.relight.exr", "textures/atlas.vertex.npz",
              "demo_relight_90.png", "textures_baked_90/atlas.bounce1.exr"):
        assert (out / f).is_file(), f
    # Step 3 baked relightable bounces (the default); step 5 relit them and rebaked a
    # baked bounce in a copy: the saved .blend's textures are still step 3's.
    assert not (out / "textures_relightable_90").exists()
    # the folder is portable: the World's HDRI beside the .blend, //-relative (it pointed into .venv)
    code = ("import bpy, sys; bpy.ops.wm.open_mainfile(filepath=sys.argv[1]); "
            "print('WORLD', [n.image.filepath for n in bpy.context.scene.world.node_tree.nodes "
            "if getattr(n, 'image', None)])")
    w = subprocess.run([sys.executable, "-c", code, str(out / "prtt_demo.blend")], capture_output=True, text=True,
                       timeout=120, env=dict(os.environ, PYTHONPATH=ROOT))
    assert "WORLD ['//forest.exr']" in w.stdout and (out / "forest.exr").is_file(), w.stdout[-2000:]
    import json
    home, turned = (json.loads((out / d / "manifest.json").read_text())["bounce"]
                    for d in ("textures", "textures_baked_90"))
    assert home["files"] == ["atlas.relight.exr"] and home["mode"] == "relightable" and home["light_hash"] is None
    assert turned.get("mode", "baked") == "baked" and turned["light_hash"]      # the rebake saw the turned World
    assert not any(n.endswith(".bounce1.exr") for n in os.listdir(out / "textures"))
    diff = float(re.search(r"the two pictures differ by ([0-9.]+) %", r.stdout).group(1))
    assert 0.0 < diff < 10.0, diff
    import matplotlib.image as mpimg
    frag, vert = mpimg.imread(out / "demo_tpfl.png"), mpimg.imread(out / "demo_vertex-tpfl.png")
    assert frag.shape == (90, 160, 4) and frag[..., 3].mean() > 0.5
    # The floor's four vertices sit in the room's corners: the vertex baseline is much darker there.
    floor_rows = slice(75, 88)
    assert frag[floor_rows, 40:120, :3].mean() > 1.5 * vert[floor_rows, 40:120, :3].mean()
    assert np.isfinite(frag).all()


@pytest.mark.parametrize("size", [(160, 90), (320, 180), (960, 540)])
def test_captions_do_not_overlap_at_any_size(size):
    """The demo's captions at --size 160x90 ran into each other (issue 50):
    wrapped to their half, no two text boxes overlap, all inside the figure."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from prtt_addon.dev.demo import labelled_figure
    w, h = size
    img = np.zeros((h, w, 4), np.float32)
    img[..., 3] = 1.0
    fig = labelled_figure(plt, img, img, ("vertex TPFL: per-vertex transfer at the 21024 triangles' vertices "
                                          "(the traditional baseline)",
                                          "PRTT: fragment TPFL, 1024² transfer texture + 1 bounce"),
                          title="room-class scene, 21024 triangles; 5 SH bands, 256 rays/texel, 64 bounce rays; "
                                "light: World image 'forest.exr' x1; exposure 0")
    fig.canvas.draw()
    r = fig.canvas.get_renderer()
    texts = list(fig.texts)
    boxes = [t.get_window_extent(r) for t in texts]
    frame = fig.bbox
    for i, a in enumerate(boxes):
        assert a.x0 >= frame.x0 - 1 and a.x1 <= frame.x1 + 1 and a.y0 >= frame.y0 - 1 and a.y1 <= frame.y1 + 1, \
            (size, texts[i].get_text())
        for j in range(i + 1, len(boxes)):
            assert not a.overlaps(boxes[j]), (size, texts[i].get_text(), texts[j].get_text())
        for ax in fig.axes:                                    # and not over the pictures
            assert a.y0 >= ax.get_window_extent(r).y1 - 0.5, (size, texts[i].get_text())
    assert [round(ax.get_window_extent(r).height) for ax in fig.axes] == [h, h]     # the pictures at their size
    plt.close(fig)
