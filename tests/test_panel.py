"""The N-panel by Blender's conventions (issue 14): the panels' draw code runs
headless against a recording layout (Blender has no UI regions in background
mode), and the operators say why they are disabled."""
import pytest

from tests.blender_util import addon_bpy

pytestmark = pytest.mark.blender


class Layout:
    """Records what a draw() puts in a layout; sub-layouts record into the same log."""

    def __init__(self, log=None, depth=0):
        self.__dict__["log"] = log if log is not None else []
        self.__dict__["depth"] = depth
        self.__dict__["flags"] = {}

    def __setattr__(self, name, value):
        self.flags[name] = value

    def __getattr__(self, name):
        if name in ("column", "row", "box", "split", "column_flow", "grid_flow"):
            return lambda *a, **k: Layout(self.log, self.depth + 1)

        def record(*args, **kwargs):
            self.log.append((name, args, kwargs))
            return Layout(self.log, self.depth + 1)
        return record

    def props(self):
        return [a[1] for name, a, _ in self.log if name in ("prop", "prop_search")]


def _draw(bpy, cls):
    layout = Layout()
    # Stands in for the registered panel: its layout, and the class's own attributes.
    panel = type("P", (), {"layout": layout, "__getattr__": lambda _self, name: getattr(cls, name)})()
    cls.draw(panel, bpy.context)
    return layout


def test_panel_order_split_and_closed_subpanels():
    bpy = addon_bpy()
    bpy.ops.mesh.primitive_monkey_add()
    from prtt_addon.blender.ui import panels
    children = [c for c in panels._CLASSES if getattr(c, "bl_parent_id", "") == "PRTT_PT_main"]
    assert [c.bl_label for c in sorted(children, key=lambda c: c.bl_order)] == \
        ["Unwrap", "Bake", "Preview", "Last Bake"]
    subs = {c.bl_label: c for c in panels._CLASSES if getattr(c, "bl_parent_id", "") == "PRTT_PT_bake"}
    assert set(subs) == {"Quality", "Output", "Advanced"}
    assert all("DEFAULT_CLOSED" in c.bl_options for c in subs.values())
    seen = set()
    for cls in panels._CLASSES:
        if cls.bl_label == "Last Bake":
            continue
        layout = _draw(bpy, cls)
        assert layout.flags.get("use_property_split") is True, cls.bl_label
        assert layout.flags.get("use_property_decorate") is False, cls.bl_label
        seen.update(layout.props())
    # Sky Sun is drawn where it applies: a World with a Sky Texture's sun disc
    from prtt_addon.dev.bench.sun_cycles import sky_world
    world = bpy.context.scene.world
    bpy.context.scene.world = sky_world(bpy, 0.5)
    sky_props = _draw(bpy, panels.PRTT_PT_bake).props()
    assert "sky_sun" in sky_props and "hdri_sun" not in sky_props
    seen.update(sky_props)
    bpy.context.scene.world = world
    st = bpy.context.scene.prtt
    # every scene setting is drawn somewhere (state properties excepted)
    drawn_or_state = seen | {"status", "progress", "baking", "last_bake", "existing_uv_map", "builtin_environment"}
    assert {p.identifier for p in st.bl_rna.properties if p.identifier not in ("rna_type", "name")} <= drawn_or_state
    # the main panel leads to Unwrap before Bake: the unwrap operator is in Unwrap, bake in Bake
    assert ("operator", ("prtt.unwrap",), {"icon": "UV"}) in _draw(bpy, panels.PRTT_PT_unwrap).log
    assert any(a == ("prtt.bake_transfer",) for n, a, _ in _draw(bpy, panels.PRTT_PT_bake).log if n == "operator")


def test_source_uv_map_is_chosen_from_the_objects_maps():
    bpy = addon_bpy()
    bpy.ops.mesh.primitive_monkey_add()
    from prtt_addon.blender.ui import panels
    bpy.context.scene.prtt.unwrap_method = "EXISTING"
    log = _draw(bpy, panels.PRTT_PT_unwrap).log
    (search,) = [(a, k) for n, a, k in log if n == "prop_search"]
    assert search[0][1:] == ("existing_uv_map", bpy.context.object.data, "uv_layers")


def test_disabled_operators_say_why():
    bpy = addon_bpy()
    with pytest.raises(RuntimeError, match="Select one or more mesh objects"):
        bpy.ops.prtt.unwrap()
    with pytest.raises(RuntimeError, match="Nothing baked yet"):
        bpy.ops.prtt.render_preview()
    with pytest.raises(RuntimeError, match="No bake is running"):
        bpy.ops.prtt.cancel_bake()
    assert "UNDO" in bpy.types.PRTT_OT_bake_transfer.bl_options
    assert "UNDO" in bpy.types.PRTT_OT_unwrap.bl_options


def test_images_the_addon_makes_survive_save_and_reload(tmp_path):
    import numpy as np
    bpy = addon_bpy()
    from tests import real_scenes as rs
    st = bpy.context.scene.prtt
    st.output_dir, st.resolution, st.rays, st.bounces = str(tmp_path / "out"), 16, 16, 0
    rs.floor(bpy, 4.0).data.uv_layers.new(name="PRTT")
    rs.add_object(bpy, "Box", rs.cube_mesh(bpy, "box"), location=(0, 0, 0.5)).data.uv_layers.new(name="PRTT")
    from prtt_addon.blender.bake.run import bake_blocking
    assert bake_blocking(bpy.context).status == "done"
    before = {}
    for name in ("PRTT AO Floor", "PRTT AO Box"):
        img = bpy.data.images[name]
        a = np.empty(len(img.pixels), np.float32)
        img.pixels.foreach_get(a)
        assert a[0::4].min() < 0.99                   # the box darkens the floor: not a blank image
        before[name] = a
    path = str(tmp_path / "s.blend")
    bpy.ops.wm.save_as_mainfile(filepath=path)
    bpy.ops.wm.open_mainfile(filepath=path)
    for name, a in before.items():
        img = bpy.data.images[name]
        b = np.empty(len(img.pixels), np.float32)
        img.pixels.foreach_get(b)
        np.testing.assert_allclose(b, a, atol=1e-3)
