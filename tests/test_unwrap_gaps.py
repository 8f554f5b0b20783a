"""Padding that holds (issue 53): the unwrap's islands are as many texels
apart as docs/format.md says (`padding`: the Margin, raised to the bake's
needs: 6 by default), measured on the UV map at each resolution and with
every method, on meshes the unwrap was not tuned for.

Before: Lightmap Pack left 0.77 / 1.54 / 3.08 texels at 256² / 512² / 1024²
(a margin fixed in UV units), xatlas 13 where 6 were asked (it pads each
chart, so twice the space). Smart UV Project keeps Blender's SCALED margin,
which follows the islands' scale (7.25 texels on the demo room, 6.8-13 on
the monkey, but 2.5 on a cube and 3.2 on a torus): its exact FRACTION
margin packs much sparser, so it stays open in issue 53's note."""
import numpy as np
import pytest

from tests.blender_util import addon_bpy, select_only

pytestmark = pytest.mark.blender


def test_gap_measure_against_a_drawn_layout():
    """core/texels/uv_gaps on squares placed by hand: 3 and 5 texels apart, a
    touching pair (one island: shared corners), and crossing triangles."""
    from prtt_addon.core.texels.uv_gaps import island_gaps, triangle_distances, uv_islands

    def square(x0, y0, s):
        return np.array([[[x0, y0], [x0 + s, y0], [x0 + s, y0 + s]], [[x0, y0], [x0 + s, y0 + s], [x0, y0 + s]]])
    r = 512
    uv = np.concatenate([square(0.1, 0.1, 0.2), square(0.3 + 3 / r, 0.1, 0.2), square(0.1, 0.3 + 5 / r, 0.1)])
    assert len(set(uv_islands(uv))) == 3
    assert np.allclose(island_gaps(uv, r), [3, 3, 3, 3, 5, 5])
    a = np.array([[[0, 0], [4, 0], [0, 4]]], float)
    assert triangle_distances(a, a + [[1, 1]])[0] == 0.0                     # overlapping
    assert np.isclose(triangle_distances(a, a + [[10, 0]])[0], 6.0)           # 4 -> 10 along x
    assert np.isclose(triangle_distances(a, -a + [[6, 6]])[0], 2 * np.sqrt(2))  # x+y=4 against x+y=8


def _scene(bpy, kind):
    bpy.ops.wm.read_factory_settings(use_empty=True)
    if kind == "torus":
        bpy.ops.mesh.primitive_torus_add(major_segments=48, minor_segments=24)
    elif kind == "monkey":
        bpy.ops.mesh.primitive_monkey_add()
        bpy.ops.object.subdivision_set(level=1)
        bpy.ops.object.convert(target="MESH")
    elif kind == "triangles":                    # Lightmap Pack pairs triangles into boxes
        bpy.ops.mesh.primitive_ico_sphere_add(subdivisions=2)
        bpy.ops.mesh.primitive_cone_add(location=(3, 0, 0))
    else:
        bpy.ops.mesh.primitive_cube_add()
        bpy.ops.mesh.primitive_plane_add(size=5, location=(0, 0, -1))
    return [o for o in bpy.context.scene.objects if o.type == "MESH"]


@pytest.mark.parametrize("method", ["SMART", "LIGHTMAP", "XATLAS"])
@pytest.mark.parametrize("kind", ["torus", "monkey", "cube", "triangles"])
def test_islands_are_the_padding_apart(method, kind):
    bpy = addon_bpy()
    from prtt_addon.blender.scene.uv_maps import _tri_uvs, bake_downscale, margin_texels
    from prtt_addon.core.texels.uv_gaps import island_gaps
    for res in (512, 1024):
        objects = _scene(bpy, kind)
        st = bpy.context.scene.prtt
        st.resolution, st.texture_sets, st.unwrap_method = res, "ATLAS", method
        select_only(bpy, objects)
        bpy.context.view_layer.objects.active = objects[0]
        assert bpy.ops.prtt.unwrap() == {"FINISHED"}
        want = margin_texels(st.padding, st.dilate, bake_downscale(st))
        gap = island_gaps(np.concatenate([_tri_uvs(o) for o in objects]), res)
        # xatlas packs on whole texels and leaves
        # some charts further apart, never the twice-the-gap it left before.
        # Lightmap Pack: quads exact (their boxes on a grid of whole divisions);
        # paired triangles sit from one inset to sqrt(2) insets across their box.
        # Smart UV Project: Blender's scaled margin, raised until the map holds
        # the gap (uv_maps._smart_project; before, 2.5 texels on the cube, 3.2 on
        # the torus), not much more (the packing stays as dense as it can).
        most = {"SMART": 2 * want, "XATLAS": 2 * want - 0.5,
                "LIGHTMAP": (np.sqrt(2) * want if kind == "triangles" else want) + 0.2}[method]
        print(method, kind, res, round(float(gap.min()), 2))
        assert want - 0.05 <= gap.min() <= most, (method, kind, res, want, gap.min())


def test_lightmap_pack_seams_are_no_worse_than_smart_uv_projects():
    """The picture at UV seams against a traced ground truth (bench/seam_error:
    a torus at 512², TPFL, pixels within a texel of an island border). Before
    the fix Lightmap Pack's 1.5-texel gaps gave a seam p99 of 1.46 % against
    Smart UV Project's 0.94 %; after, 0.87 % against 0.83 %."""
    addon_bpy()
    from prtt_addon.dev.bench.seam_error import torus_errors
    smart, lightmap = torus_errors("SMART"), torus_errors("LIGHTMAP")
    print({"smart": smart, "lightmap": lightmap})
    assert lightmap["seam"]["pixels"] > 1000 and smart["seam"]["pixels"] > 500
    assert lightmap["seam"]["mean"] <= 1.25 * smart["seam"]["mean"]
    assert lightmap["seam"]["p99"] <= 1.25 * smart["seam"]["p99"]
    assert smart["seam"]["p99"] < 0.02


def test_bench_scenes_keep_the_layout_they_were_measured_with():
    """meshgen.chart_gap turns the benchmark scenes' xatlas padding into the gap
    core's unwrap takes now: xatlas gets the same padding at the first try and
    at every halving of a retry (a trailing extra try at 0 aside), so the
    scenes, the bake identity record and the benchmark figures keep their
    layouts."""
    from prtt_addon.core.texels.unwrap import xatlas_padding
    from prtt_addon.dev.bench.meshgen import chart_gap

    def halvings(p):
        out = [p]
        while p:
            p //= 2
            out.append(p)
        return out

    for p in range(0, 65):
        asked = [xatlas_padding(g) for g in halvings(chart_gap(p))]
        assert asked[:len(halvings(p))] == halvings(p) and not any(asked[len(halvings(p)):]), (p, asked)


def test_the_measure_for_the_unwrap_stays_in_its_budget():
    """20,000 one-triangle islands in a 64² texture (the demo room's unwrap at
    a tiny resolution): hundreds of triangles a cell, whose pairs would take
    gigabytes; the unwrap's measure says it cannot (None) and allocates no
    more than its budget. A few islands are measured as usual."""
    import tracemalloc

    from prtt_addon.core.texels.uv_gaps import UNWRAP_BUDGET, narrowest_gap
    rng = np.random.default_rng(0)
    centres = rng.random((20000, 1, 2))
    many = centres + rng.random((20000, 3, 2)) * 0.002
    tracemalloc.start()
    got = narrowest_gap(many, 64, within=7.0, budget=UNWRAP_BUDGET)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert got is None and peak < 200 * 2**20, (got, peak)
    few = np.array([[[0.1, 0.1], [0.2, 0.1], [0.1, 0.2]], [[0.3, 0.1], [0.4, 0.1], [0.3, 0.2]]])
    assert abs(narrowest_gap(few, 100, within=16.0, budget=UNWRAP_BUDGET) - 10.0) < 1e-9
