"""Settings stored in the .blend: ``scene.prtt`` and ``object.prtt``."""
import bpy
from bpy.props import (BoolProperty, EnumProperty, FloatProperty, IntProperty, PointerProperty,
                       StringProperty)

#: Name of the UV map PRTT bakes into; unwrapping writes only this map.
UV_MAP = "PRTT"


def _builtin_env_items(self, context):
    from ..core.envmap import builtin_environments
    names = sorted(builtin_environments()) or ["forest"]
    return [(n, n.capitalize(), f"Blender's studio light '{n}'") for n in names]


def redraw_viewports(context) -> None:
    """Ask every 3D viewport to redraw (no-op in background mode: no windows)."""
    wm = context.window_manager
    for window in (wm.windows if wm is not None else []):
        for area in window.screen.areas:
            if area.type == "VIEW_3D":
                area.tag_redraw()


def _redraw(self, context):
    redraw_viewports(context)


#: Property value of each preview mode -> shader mode name.
PREVIEW_MODES = {"TPFL": "tpfl", "TP": "tp", "VERTEX_TPFL": "vertex-tpfl", "VERTEX_TP": "vertex-tp",
                 "DIFFUSE": "diffuse"}


class PRTTSceneSettings(bpy.types.PropertyGroup):
    # --- unwrap -------------------------------------------------------------------
    unwrap_method: EnumProperty(
        name="Method", default="SMART",
        items=[("EXISTING", "Existing UV Map", "Copy an existing UV map into the PRTT map"),
               ("SMART", "Smart UV Project", "Blender's Smart UV Project, packed per object"),
               ("LIGHTMAP", "Lightmap Pack", "Blender's Lightmap Pack: one island per face"),
               ("XATLAS", "xatlas", "xatlas charts and packing, in-process")])
    existing_uv_map: StringProperty(
        name="Source UV Map", default="",
        description="UV map copied by 'Existing UV Map' (empty: the active render map)")
    padding: IntProperty(name="Margin (texels)", default=4, min=0, max=64,
                         description="Space between UV islands, in texels of the object's resolution")
    texel_density: FloatProperty(
        name="Texel Density", default=0.0, min=0.0, soft_max=2048.0,
        description="Texels per metre; > 0 sets each object's resolution from its surface "
                    "area (a power of two, up to the scene resolution); 0 = scene resolution")
    # --- bake ---------------------------------------------------------------------
    resolution: IntProperty(name="Resolution", default=1024, min=8, max=16384,
                            description="Texels per side of each transfer texture")
    bands: IntProperty(name="SH Bands", default=5, min=1, max=8,
                       description="Spherical-harmonic bands (5 = 25 coefficients, the paper's choice)")
    rays: IntProperty(name="Rays", default=256, min=16, max=65536,
                      description="Rays per texel (the maximum when adaptive)")
    adaptive: BoolProperty(name="Adaptive", default=False,
                           description="Stop each texel once its estimate is precise enough")
    adaptive_tolerance: FloatProperty(name="Tolerance", default=0.005, min=1e-5, max=1.0, precision=4,
                                      description="RMS standard error of the coefficients to stop at")
    bounces: IntProperty(name="Bounces", default=1, min=0, max=8,
                         description="Inter-reflection textures (they bake the light and materials in)")
    bounce_rays: IntProperty(name="Bounce Rays", default=64, min=1, max=16384)
    texture_sets: EnumProperty(
        name="Texture Sets", default="OBJECT",
        items=[("OBJECT", "Per Object", "One texture per object"),
               ("ATLAS", "One Atlas", "Every object in one shared texture")])
    vertex_transfer: BoolProperty(
        name="Vertex Transfer", default=False,
        description="Also bake per-vertex transfer, for the traditional vertex-shader baselines of the preview")
    normal_maps: BoolProperty(name="Normal Maps", default=True,
                              description="Bake with the materials' tangent-space normal maps")
    dilate: IntProperty(name="Dilation", default=3, min=0, max=64,
                        description="Texels of padding around UV islands")
    storage: EnumProperty(name="Storage", default="HALF",
                          items=[("HALF", "Half", "16-bit float EXR"), ("FLOAT", "Float", "32-bit float EXR")])
    output_dir: StringProperty(name="Output Folder", default="//prtt/", subtype="DIR_PATH",
                               description="Where the textures go ('//' = next to the .blend)")
    selection_only: BoolProperty(name="Selected Only", default=False,
                                 description="Bake only selected objects (the others still cast shadows)")
    light_source: EnumProperty(
        name="Light", default="WORLD",
        items=[("WORLD", "World", "The scene World's environment texture or colour"),
               ("BUILTIN", "Studio HDRI", "One of Blender's bundled studio HDRIs")])
    builtin_environment: EnumProperty(name="HDRI", items=_builtin_env_items)
    # --- viewport preview -----------------------------------------------------------
    preview: BoolProperty(name="Preview", default=False, update=_redraw,
                          description="Draw baked objects with PRT shading in the 3D viewport")
    preview_mode: EnumProperty(
        name="Mode", default="TPFL", update=_redraw,
        items=[("TPFL", "TPFL (fragment)", "Triple product with fixed light per pixel, transfer textures"),
               ("TP", "TP (fragment)", "Full triple product per pixel (slower; same image as TPFL)"),
               ("VERTEX_TPFL", "TPFL (vertex)", "Traditional baseline: per-vertex transfer, colour interpolated"),
               ("VERTEX_TP", "TP (vertex)", "Traditional baseline with the full triple product per vertex"),
               ("DIFFUSE", "Diffuse", "Double product only: diffuse shading, no glossy lobe")])
    preview_bounces: BoolProperty(name="Inter-reflections", default=True, update=_redraw,
                                  description="Add the bounce textures (when the bake made them)")
    # --- state ----------------------------------------------------------------------
    status: StringProperty(name="Status", default="")
    progress: FloatProperty(name="Progress", default=0.0, min=0.0, max=1.0, subtype="FACTOR")
    baking: BoolProperty(default=False)
    last_bake: StringProperty(default="", description="JSON summary of the last bake")


class PRTTObjectSettings(bpy.types.PropertyGroup):
    bake: BoolProperty(name="Bake Transfer", default=True,
                       description="Give this object a transfer texture (otherwise it only casts shadows)")
    resolution: IntProperty(name="Resolution Override", default=0, min=0, max=16384,
                            description="Texels per side for this object (0 = scene setting)")


_CLASSES = (PRTTSceneSettings, PRTTObjectSettings)


def register():
    for c in _CLASSES:
        bpy.utils.register_class(c)
    bpy.types.Scene.prtt = PointerProperty(type=PRTTSceneSettings)
    bpy.types.Object.prtt = PointerProperty(type=PRTTObjectSettings)


def unregister():
    del bpy.types.Object.prtt
    del bpy.types.Scene.prtt
    for c in reversed(_CLASSES):
        bpy.utils.unregister_class(c)
