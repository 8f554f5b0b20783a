"""Settings stored in the .blend: ``scene.prtt`` and ``object.prtt``."""
import bpy
from bpy.props import BoolProperty, EnumProperty, FloatProperty, IntProperty, PointerProperty, StringProperty

from ...core import settings_schema
from ...core.light.envmap import builtin_environments
from ..shared import redraw_viewports
from ..versions import RELATIVE_PATH_OPTIONS

_ENV_ITEMS: list = []


def _builtin_env_items(self, context):
    """Blender's studio HDRIs, listed once: the callback runs on every redraw, and
    Blender needs the returned strings to stay referenced from Python (a fresh
    list each time would also scan the datafiles folder each time)."""
    if not _ENV_ITEMS:
        names = sorted(builtin_environments()) or ["forest"]
        _ENV_ITEMS.extend((n, n.capitalize(), f"Blender's studio light '{n}'") for n in names)
    return _ENV_ITEMS


def _redraw(self, context):
    redraw_viewports(context)


def schema_property(p):
    """A ``bpy.props`` property from a settings_schema.UiProp."""
    common = {"name": p.label, "description": p.description}
    if p.kind == "bool":
        return BoolProperty(default=p.default, **common)
    if p.kind == "enum":
        return EnumProperty(items=list(p.items), default=p.default, **common)
    limits = {k: v for k, v in (("min", p.lo), ("max", p.hi), ("soft_min", p.soft_lo), ("soft_max", p.soft_hi))
              if v is not None}
    if p.kind == "int":
        return IntProperty(default=p.default, **{k: int(v) for k, v in limits.items()}, **common)
    if p.kind == "float":
        return FloatProperty(default=p.default, **limits, **({"precision": p.precision} if p.precision else {}),
                             **common)
    raise ValueError(f"no Blender property for a {p.kind!r} setting ({p.name})")


def _scene_annotations() -> dict:
    """scene.prtt's properties. The bake settings (resolution, bands, rays, adaptive,
    tolerance, bounces, bounce rays, vertex transfer, normal maps, dilation, storage,
    margin, texel density) come from core/settings_schema.py: their ranges, soft
    limits, defaults and tooltips are declared there once."""
    unwrap = {
        "unwrap_method": EnumProperty(
            name="Method", default="SMART",
            description="How Unwrap lays out the PRTT UV map (every method ends with no overlapping texels)",
            items=[("EXISTING", "Existing UV Map", "Copy an existing UV map into the PRTT map"),
                   ("SMART", "Smart UV Project", "Blender's Smart UV Project, packed per object"),
                   ("LIGHTMAP", "Lightmap Pack", "Blender's Lightmap Pack: one island per face"),
                   ("XATLAS", "xatlas", "xatlas charts and packing, in a child process")]),
        "existing_uv_map": StringProperty(
            name="Source UV Map", default="",
            description="UV map copied by 'Existing UV Map' (empty: the active render map)"),
    }
    settings = {p.name: schema_property(p) for p in settings_schema.ui_properties()}
    bake = {
        "texture_sets": EnumProperty(
            name="Texture Sets", default="OBJECT",
            description="One texture set per object, or one atlas for all objects with a PRTT map "
                        "(instances and generated-UV objects always get sets of their own)",
            items=[("OBJECT", "Per Object", "One texture per object"),
                   ("ATLAS", "One Atlas", "Every object in one shared texture")]),
        "output_dir": StringProperty(name="Output Folder", default="//prtt/", subtype="DIR_PATH",
                                     description="Where the textures go ('//' = next to the .blend)",
                                     **RELATIVE_PATH_OPTIONS),
        "dask_scheduler": StringProperty(
            name="Dask Scheduler", default="",
            description="Run the bake's ray work on a Dask cluster: local or local:N (worker processes on this "
                        "machine), or tcp://HOST:PORT of a running scheduler; empty = this machine's cores. "
                        "Needs the optional packages dask and distributed; the textures are the same bits"),
        "selection_only": BoolProperty(name="Selected Only", default=False,
                                       description="Bake only selected objects (the others still cast shadows)"),
        "light_source": EnumProperty(
            name="Light", default="WORLD",
            description="The environment light the preview and the bounce bake use",
            items=[("WORLD", "World", "The scene World's environment texture or colour"),
                   ("BUILTIN", "Studio HDRI", "One of Blender's bundled studio HDRIs")]),
        "builtin_environment": EnumProperty(name="HDRI", items=_builtin_env_items,
                                            description="One of the studio HDRIs Blender ships"),
        "sky_sun": BoolProperty(
            name="Sky Sun", default=True,
            description="Bake the sun disc of the World's Sky Texture as the sun: its shadows as a mask, its "
                        "light per pixel (as a Sun lamp's). Off: the disc stays in the World's SH light, a soft "
                        "blob without shadows. A Sun lamp in the scene is the sun either way"),
        "hdri_sun": BoolProperty(
            name="HDRI Sun", default=False,
            description="Take the World image's sun (its brightest compact region, at least 5 % of its light) "
                        "out of the SH light and bake it as the sun: crisp shadows and its light per pixel. "
                        "A Sun lamp in the scene is the sun instead"),
    }
    preview = {
        "preview": BoolProperty(name="Preview", default=False, update=_redraw,
                                description="Draw baked objects with PRT shading in the 3D viewport"),
        "preview_mode": EnumProperty(
            name="Mode", default="TPFL", update=_redraw,
            description="How the viewport shades baked objects",
            items=[("TPFL", "TPFL (fragment)", "Triple product with fixed light per pixel, transfer textures"),
                   ("TP", "TP (fragment)", "Full triple product per pixel (slower; same image as TPFL)"),
                   ("VERTEX_TPFL", "TPFL (vertex)",
                    "Traditional baseline: per-vertex transfer, colour interpolated"),
                   ("VERTEX_TP", "TP (vertex)", "Traditional baseline with the full triple product per vertex"),
                   ("DIFFUSE", "Diffuse", "Double product only: diffuse shading, no glossy lobe")]),
        "preview_bounces": BoolProperty(name="Inter-reflections", default=True, update=_redraw,
                                        description="Add the bounce textures (when the bake made them)"),
    }
    state = {
        "status": StringProperty(name="Status", default=""),
        "progress": FloatProperty(name="Progress", default=0.0, min=0.0, max=1.0, subtype="FACTOR"),
        "baking": BoolProperty(default=False),
        "last_bake": StringProperty(default="", description="JSON summary of the last bake"),
    }
    clash = (set(unwrap) | set(bake) | set(preview) | set(state)) & set(settings)
    if clash:
        raise RuntimeError(f"scene.prtt properties declared twice: {sorted(clash)}")
    return {**unwrap, **settings, **bake, **preview, **state}


#: scene.prtt (a class built from the annotations above: Blender reads them at register_class).
PRTTSceneSettings = type("PRTTSceneSettings", (bpy.types.PropertyGroup,),
                         {"__annotations__": _scene_annotations(), "__module__": __name__,
                          "__doc__": "PRTT settings of a scene (scene.prtt)"})


_RES = settings_schema.get("resolution")


class PRTTObjectSettings(bpy.types.PropertyGroup):
    bake: BoolProperty(name="Bake Transfer", default=True,
                       description="Give this object a transfer texture (otherwise it only casts shadows)")
    resolution: IntProperty(name="Resolution Override", default=0, min=0, max=_RES.hi, soft_max=_RES.ui.soft_hi,
                            description=f"Texels per side of this object's texture (1 to {_RES.hi}; "
                                        f"0 = the scene's Resolution or Texel Density)")


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
