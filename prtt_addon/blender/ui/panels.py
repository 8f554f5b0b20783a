"""The N-panel: View3D > Sidebar > PRTT."""
import json

import bpy
from bpy.app.handlers import persistent

from ..preview import draw as preview_draw
from ..preview import drawlist
from ..scene import world_panorama
from ..scene.world import world_has_sky_sun


class _PRTTPanel:
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "PRTT"


def _split(layout):
    """Blender's property-split layout: labels left, values right, no decorators."""
    layout.use_property_split = True
    layout.use_property_decorate = False
    return layout


def draw_progress(layout, st) -> None:
    """The running bake as a bar (panel and status bar) with its Cancel button."""
    row = layout.row(align=True)
    row.progress(factor=st.progress, type="BAR", text=f"{st.status} {100 * st.progress:.0f}%")
    row.operator("prtt.cancel_bake", text="", icon="CANCEL")


class PRTT_PT_main(_PRTTPanel, bpy.types.Panel):
    """The active object's PRTT settings; the steps follow as subpanels."""

    bl_label = "PRTT"

    def draw(self, context):
        layout = _split(self.layout)
        ob = context.object
        if ob is None or ob.type not in {"MESH", "CURVE", "SURFACE", "META", "FONT", "EMPTY"}:
            layout.label(text="Select an object to bake", icon="INFO")
            return
        col = layout.column()
        col.label(text=ob.name, icon="OBJECT_DATA")
        col.prop(ob.prtt, "bake")
        sub = col.column()
        sub.active = ob.prtt.bake
        sub.prop(ob.prtt, "resolution")
        if ob.type == "MESH":
            has_uv = "PRTT" in ob.data.uv_layers
            col.label(text="PRTT UV map: " + ("present" if has_uv else "missing, Unwrap below"),
                      icon="CHECKMARK" if has_uv else "ERROR")
        elif ob.type != "EMPTY":
            col.label(text="UVs generated at bake time", icon="INFO")


class PRTT_PT_unwrap(_PRTTPanel, bpy.types.Panel):
    bl_label = "Unwrap"
    bl_parent_id = "PRTT_PT_main"
    bl_order = 0

    def draw(self, context):
        st = context.scene.prtt
        layout = _split(self.layout)
        col = layout.column()
        col.prop(st, "unwrap_method")
        if st.unwrap_method == "EXISTING":
            ob = context.object
            if ob is not None and ob.type == "MESH":
                col.prop_search(st, "existing_uv_map", ob.data, "uv_layers", text="Source UV Map")
            else:
                col.prop(st, "existing_uv_map", text="Source UV Map")
        col.prop(st, "padding")
        col.prop(st, "texel_density")
        layout.operator("prtt.unwrap", icon="UV")


class PRTT_PT_bake(_PRTTPanel, bpy.types.Panel):
    bl_label = "Bake"
    bl_parent_id = "PRTT_PT_main"
    bl_order = 1

    def draw(self, context):
        st = context.scene.prtt
        layout = _split(self.layout)
        col = layout.column()
        col.prop(st, "resolution")
        col.prop(st, "texture_sets")
        col.prop(st, "light_source")
        if st.light_source == "BUILTIN":
            col.prop(st, "builtin_environment")
        elif world_has_sky_sun(context.scene):
            col.prop(st, "sky_sun")
        else:
            col.prop(st, "hdri_sun")
        if st.baking:
            draw_progress(layout, st)
        else:
            layout.operator("prtt.bake_transfer", icon="RENDER_STILL")
            if st.status:
                layout.label(text=st.status)


class PRTT_PT_bake_quality(_PRTTPanel, bpy.types.Panel):
    bl_label = "Quality"
    bl_parent_id = "PRTT_PT_bake"
    bl_options = {"DEFAULT_CLOSED"}

    def draw(self, context):
        st = context.scene.prtt
        col = _split(self.layout).column()
        col.prop(st, "bands")
        col.prop(st, "rays")
        col.prop(st, "adaptive")
        sub = col.column()
        sub.active = st.adaptive
        sub.prop(st, "adaptive_tolerance")
        col.prop(st, "bounces")
        sub = col.column()
        sub.active = st.bounces > 0
        sub.prop(st, "bounce_rays")
        sub.prop(st, "bounce_tolerance")
        sub.prop(st, "bounce_downscale")
        sub.prop(st, "bounce_mode")
        col.prop(st, "tuning")
        col.prop(st, "guiding")
        sub = col.column()
        sub.active = st.guiding
        sub.prop(st, "guided_filter")
        col.prop(st, "texel_validity")
        col.prop(st, "sun_detail")


class _SettingsList:
    """A closed Bake subpanel that lists scene settings, in the order of ``props``."""

    bl_parent_id = "PRTT_PT_bake"
    bl_options = {"DEFAULT_CLOSED"}
    props: tuple = ()

    def draw(self, context):
        col = _split(self.layout).column()
        for name in self.props:
            col.prop(context.scene.prtt, name)


class PRTT_PT_bake_output(_SettingsList, _PRTTPanel, bpy.types.Panel):
    bl_label = "Output"
    props = ("output_dir", "storage", "dilate", "vertex_transfer")


class PRTT_PT_bake_advanced(_SettingsList, _PRTTPanel, bpy.types.Panel):
    bl_label = "Advanced"
    props = ("normal_maps", "selection_only", "dask_scheduler")


class PRTT_PT_preview(_PRTTPanel, bpy.types.Panel):
    bl_label = "Preview"
    bl_parent_id = "PRTT_PT_main"
    bl_order = 2

    def draw(self, context):
        st = context.scene.prtt
        col = _split(self.layout).column()
        row = col.row(align=True)
        row.prop(st, "preview", toggle=True, icon="SHADING_RENDERED")
        row.prop(st, "preview_mode", text="")
        col.prop(st, "preview_bounces")
        col.operator("prtt.render_preview", icon="RENDER_RESULT")
        col.operator("prtt.export_gltf", icon="EXPORT")
        if not st.last_bake:
            col.label(text="Bake Transfer first", icon="INFO")
            return
        try:
            with world_panorama.drawing():   # a panel's draw may not render: a timer does
                _, status = drawlist.collect(context, use_bounces=st.preview_bounces, with_meshes=False)
        except Exception as exc:          # a panel must draw whatever happens
            col.label(text=f"{type(exc).__name__}: {exc}", icon="ERROR")
            return
        if status.light_description:
            col.label(text=f"Light: {status.light_description}", icon="WORLD")
        if status.sun_description:
            col.label(text=f"Sun: {status.sun_description}", icon="LIGHT_SUN")
        if status.lamps_description:
            col.label(text=f"Lamps: {status.lamps_description}", icon="LIGHT_POINT")
        for level, text in status.messages:
            col.label(text=text, icon={"ERROR": "ERROR", "WARNING": "ERROR"}.get(level, "INFO"))
        if st.preview:
            stats = preview_draw.last_status.get("stats")
            if preview_draw.last_status.get("error"):
                col.label(text=preview_draw.last_status["error"], icon="ERROR")
            elif stats is not None:
                col.label(text=f"{len(stats.drawn)} object(s), {stats.triangles} triangles, "
                               f"{stats.texture_bytes / 2**20:.0f} MiB of textures")
                for name, why in list(stats.skipped.items())[:4]:
                    col.label(text=f"{name}: {why}", icon="ERROR")


class PRTT_PT_last_bake(_PRTTPanel, bpy.types.Panel):
    bl_label = "Last Bake"
    bl_parent_id = "PRTT_PT_main"
    bl_options = {"DEFAULT_CLOSED"}
    bl_order = 3

    @classmethod
    def poll(cls, context):
        return bool(context.scene.prtt.last_bake)

    def draw(self, context):
        try:
            info = json.loads(context.scene.prtt.last_bake)
        except ValueError:
            return
        col = self.layout.column(align=True)
        col.label(text=f"{info.get('time', '')}, {info.get('seconds') or 0:.1f} s")
        col.label(text=f"{len(info.get('set_objects', {}))} texture set(s), light: {info.get('light') or 'none'}")
        for w in info.get("warnings", [])[:5]:
            col.label(text=w, icon="ERROR")


#: Registration order is drawing order (bl_order says it too): Unwrap -> Bake -> Preview.
_CLASSES = (PRTT_PT_main, PRTT_PT_unwrap, PRTT_PT_bake, PRTT_PT_bake_quality, PRTT_PT_bake_output,
            PRTT_PT_bake_advanced, PRTT_PT_preview, PRTT_PT_last_bake)


@persistent
def _reset_runtime_state(_):
    """A .blend saved mid-bake must not open with a bake 'running'."""
    for scene in bpy.data.scenes:
        if getattr(scene, "prtt", None) is not None and scene.prtt.baking:
            scene.prtt.baking = False
            scene.prtt.status = ""


def register():
    for c in _CLASSES:
        bpy.utils.register_class(c)
    bpy.app.handlers.load_post.append(_reset_runtime_state)


def unregister():
    if _reset_runtime_state in bpy.app.handlers.load_post:
        bpy.app.handlers.load_post.remove(_reset_runtime_state)
    for c in reversed(_CLASSES):
        bpy.utils.unregister_class(c)
