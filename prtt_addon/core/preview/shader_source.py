"""The GLSL of the viewport preview, assembled per variant (no bpy, no gpu).

The sources live in ``shaders/`` (beside the package in a checkout, inside it
in the extension zip). One file holds each formula; a *variant* is the list of
files per stage plus the resources Blender's ``GPUShaderCreateInfo`` must
declare, so the Blender side (blender/preview/shaders.py) and test harnesses build
shaders from the same description.

Modes (docs/preview.md):

=============== ================ ===================================================
mode            stage that shades transferred radiance
=============== ================ ===================================================
``tpfl``        fragment          M(L) T per pixel, transfer texture (the paper's)
``tp``          fragment          full triple product per pixel (Gaunt non-zeros)
``diffuse``     fragment          double product T . L (no glossy lobe)
``vertex-tpfl`` vertex            M(L) T per vertex, per-vertex transfer, colour
                                  interpolated (the traditional baseline)
``vertex-tp``   vertex            full triple product per vertex
=============== ================ ===================================================

Uniform blocks (std140, only vec4/mat4 members so there is no padding):

* ``PRTTView view``: ``view_projection`` (mat4), ``camera`` (xyz eye position
  and w = 1, or xyz unit direction towards the eye and w = 0 for orthographic),
  ``params`` (x exposure multiplier, y depth bias in NDC units, z K: the
  TPFL loop's run-time bound, see prtt_light.glsl; w 1 / the display gamma,
  read by the display variants).
* ``PRTTMaterial material``: ``base`` (linear rgb, metallic), ``params``
  (roughness, dielectric F0, normal-map strength, flags: 1 base-colour
  texture, 2 roughness texture, 4 normal map).
* ``PRTTLight light``: ``tpfl[3 K K4]`` (row i of M(L_c) at
  ``(c K + i) K4 + q``, four coefficients per vec4) and ``coeffs[K]`` (light
  L_k, rgb), K = bands², K4 = ceil(K / 4).

* ``PRTTSun sun`` (variants with the sun only): ``direction`` (xyz unit
  towards the sun, w = angle² / 16: the disc's widening of the GGX lobe,
  alpha'² = alpha² + w / 2: shading.shade.sun_alpha2) and ``irradiance`` (rgb W/m² facing it); with
  the sampler ``sunTex`` (r: the baked visible fraction of its disc).
* ``PRTTLamps lamps`` (variants with lamps only): ``info`` (x the number of
  lamps, at most 4), per lamp ``position`` (xyz world, w radius),
  ``intensity`` (rgb W/sr, w the spot's smoothstep scale) and ``spot`` (xyz
  unit axis, w cos half its cone; -2 for a point); with the sampler
  ``lampTex`` (channel i: the baked visible fraction of lamp i's sphere).

Push constants: ``ModelMatrix`` and ``NormalMatrix`` (mat4 each, 128 bytes:
the guaranteed minimum); NormalMatrix[3][3] is the sign of det(ModelMatrix).
"""
from __future__ import annotations

import dataclasses
import os

from ..sh.gaunt import sparse_gaunt
from ..shading.display import SHAPER_HI, SHAPER_LO

MODES = ("tpfl", "tp", "diffuse", "vertex-tpfl", "vertex-tp")
FRAGMENT_MODES = ("tpfl", "tp", "diffuse")
VERTEX_MODES = ("vertex-tpfl", "vertex-tp")

#: Preview band limit: M(L) for 8 bands is 48 KiB of uniform block (every
#: desktop GPU allows 64 KiB; 6 bands fit OpenGL's guaranteed 16 KiB).
MAX_PREVIEW_BANDS = 8

#: Width of the 2D texture holding the Gaunt tensor's non-zeros.
GAUNT_WIDTH = 1024

#: The package folder (prtt_addon/), three levels above core/preview/.
_PKG = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

TYPEDEFS = """
struct PRTTView {
  mat4 view_projection;
  vec4 camera;
  vec4 params;
};
struct PRTTMaterial {
  vec4 base;
  vec4 params;
};
struct PRTTLight {
  vec4 tpfl[%(tpfl)d];
  vec4 coeffs[%(k)d];
};
"""


def shader_dir() -> str:
    """The folder holding the .glsl files (extension: in the package; checkout: beside it)."""
    for d in (os.path.join(_PKG, "shaders"), os.path.join(os.path.dirname(_PKG), "shaders")):
        if os.path.isfile(os.path.join(d, "prtt_common.glsl")):
            return d
    raise FileNotFoundError(f"PRTT's shaders/ folder is missing (looked in {_PKG} and its parent)")


def read_source(name: str) -> str:
    with open(os.path.join(shader_dir(), name), encoding="utf-8") as f:
        return f.read()


def sh_sizes(bands: int) -> tuple[int, int]:
    """(K, K4) for ``bands``: coefficients and vec4 layers."""
    k = bands * bands
    return k, (k + 3) // 4


@dataclasses.dataclass(frozen=True)
class Variant:
    """Everything a GPUShaderCreateInfo needs for one shader."""

    name: str
    defines: tuple            # (name, value) pairs
    typedefs: str
    vertex_in: tuple          # (slot, type, name)
    interface: tuple          # (interpolation, type, name)
    samplers: tuple           # (slot, type, name)
    uniform_bufs: tuple       # (slot, struct, name)
    push_constants: tuple     # (type, name)
    vertex_files: tuple
    fragment_files: tuple

    def vertex_source(self) -> str:
        return "\n".join(read_source(f) for f in self.vertex_files)

    def fragment_source(self) -> str:
        return "\n".join(read_source(f) for f in self.fragment_files)


def gaunt_nnz(bands: int) -> int:
    return sparse_gaunt(bands).nnz


def variant(mode: str, bands: int, *, bounce: bool = False, display: bool = False, sun: bool = False,
            lamps: bool = False) -> Variant:
    """The shader for a preview ``mode`` at ``bands`` SH bands, with or without
    bounce textures; ``display``: ending in the scene's view transform
    (prtt_display.glsl, the sampler displayLut) for a colour buffer that
    encodes sRGB, instead of linear radiance; ``sun``: adding a sun's direct
    light with its baked mask (define PRTT_SUN: the sampler sunTex, the
    uniform block PRTTSun sun; fragment modes only); ``lamps``: adding point
    and spot lamps' direct light with their baked masks (define PRTT_LAMPS:
    the sampler lampTex, the uniform block PRTTLamps lamps; fragment modes only)."""
    if mode not in MODES:
        raise ValueError(f"unknown preview mode {mode!r}; use one of {', '.join(MODES)}")
    if not (isinstance(bands, int) and 1 <= bands <= MAX_PREVIEW_BANDS):
        raise ValueError(f"the preview supports 1 to {MAX_PREVIEW_BANDS} SH bands, got {bands!r}")
    k, k4 = sh_sizes(bands)
    defines = [("SH_BANDS", str(bands)), ("SH_K", str(k)), ("SH_K4", str(k4))]
    triple = mode in ("tp", "vertex-tp")
    if triple:
        defines += [("PRTT_TRIPLE_PRODUCT", "1"), ("GAUNT_NNZ", str(gaunt_nnz(bands))),
                    ("GAUNT_WIDTH", str(GAUNT_WIDTH))]
    if mode == "diffuse":
        defines.append(("PRTT_DIFFUSE", "1"))
    if bounce:
        defines.append(("PRTT_BOUNCE", "1"))
    if sun and mode not in FRAGMENT_MODES:
        raise ValueError(f"the sun is drawn in the fragment modes ({', '.join(FRAGMENT_MODES)}), not {mode!r}")
    if sun:
        defines.append(("PRTT_SUN", "1"))
    if lamps and mode not in FRAGMENT_MODES:
        raise ValueError(f"lamps are drawn in the fragment modes ({', '.join(FRAGMENT_MODES)}), not {mode!r}")
    if lamps:
        defines.append(("PRTT_LAMPS", "1"))
    if display:
        defines += [("PRTT_DISPLAY", "1"), ("PRTT_SHAPER_LO", f"{SHAPER_LO:.1f}"),
                    ("PRTT_SHAPER_HI", f"{SHAPER_HI:.1f}")]
    samplers = [(1, "FLOAT_2D", "baseTex"), (2, "FLOAT_2D", "roughTex")]
    if bounce:
        samplers.append((4, "FLOAT_2D_ARRAY", "bounceTex"))
    if triple:
        samplers.append((5, "FLOAT_2D", "gauntTex"))
    lib = ("prtt_common.glsl", "prtt_view.glsl", "prtt_light.glsl", "prtt_layering.glsl", "prtt_shade.glsl")
    if mode in FRAGMENT_MODES:
        samplers += [(0, "FLOAT_2D_ARRAY", "transferTex"), (3, "FLOAT_2D", "normalTex")]
        vertex_in = ((0, "VEC3", "pos"), (1, "VEC3", "nor"), (2, "VEC2", "uv"), (3, "VEC2", "muv"),
                     (4, "VEC2", "nuv"), (5, "VEC4", "tan"))
        interface = (("smooth", "VEC3", "wpos"), ("smooth", "VEC3", "wnor"), ("smooth", "VEC4", "wtan"),
                     ("smooth", "VEC2", "prtt_uv"), ("smooth", "VEC2", "mat_uv"), ("smooth", "VEC2", "nm_uv"))
        vfiles = ("prtt_view.glsl", "prtt_surface_vert.glsl")
        ffiles = lib + ("prtt_surface_frag.glsl",)
    else:
        samplers.append((6, "FLOAT_2D_ARRAY", "vertexTex"))
        vertex_in = ((0, "VEC3", "pos"), (1, "VEC3", "nor"), (2, "VEC2", "uv"), (3, "VEC2", "muv"),
                     (4, "FLOAT", "vidx"))
        interface = (("smooth", "VEC3", "vcolor"),)
        vfiles = lib + ("prtt_vertex_vert.glsl",)
        ffiles = ("prtt_vertex_frag.glsl",)
    if sun:
        samplers.append((8, "FLOAT_2D", "sunTex"))
    if lamps:
        samplers.append((9, "FLOAT_2D", "lampTex"))
    if display:
        samplers.append((7, "FLOAT_3D", "displayLut"))
        ffiles = ffiles[:-1] + ("prtt_display.glsl",) + ffiles[-1:]
    return Variant(
        name=(f"prtt_{mode.replace('-', '_')}_b{bands}{'_bounce' if bounce else ''}{'_display' if display else ''}"
              f"{'_sun' if sun else ''}{'_lamps' if lamps else ''}"),
        defines=tuple(defines), typedefs=TYPEDEFS % {"tpfl": 3 * k * k4, "k": k} + (SUN_TYPEDEFS if sun else "")
        + (LAMP_TYPEDEFS if lamps else ""),
        vertex_in=vertex_in, interface=interface, samplers=tuple(sorted(samplers)),
        uniform_bufs=((0, "PRTTView", "view"), (1, "PRTTMaterial", "material"), (2, "PRTTLight", "light"))
        + (((3, "PRTTSun", "sun"),) if sun else ()) + (((4, "PRTTLamps", "lamps"),) if lamps else ()),
        push_constants=(("MAT4", "ModelMatrix"), ("MAT4", "NormalMatrix")),
        vertex_files=vfiles, fragment_files=ffiles)


def depth_variant() -> Variant:
    """The depth pre-pass: positions only, same clip-space code as shading."""
    return Variant(
        name="prtt_depth", defines=(), typedefs=TYPEDEFS % {"tpfl": 1, "k": 1},
        vertex_in=((0, "VEC3", "pos"),), interface=(), samplers=(),
        uniform_bufs=((0, "PRTTView", "view"),), push_constants=(("MAT4", "ModelMatrix"),),
        vertex_files=("prtt_view.glsl", "prtt_depth_vert.glsl"), fragment_files=("prtt_depth_frag.glsl",))


def light_block_bytes(bands: int) -> int:
    """Size of the PRTTLight uniform block for ``bands``."""
    k, k4 = sh_sizes(bands)
    return 16 * (3 * k * k4 + k)


SUN_TYPEDEFS = """
struct PRTTSun {
  vec4 direction;
  vec4 irradiance;
};
"""

#: Point and spot lamps (prtt_shade.glsl lamp_light; pack.lamp_block): at most core.light.lamp.MAX_LAMPS.
LAMP_TYPEDEFS = """
struct PRTTLamps {
  vec4 info;
  vec4 position[4];
  vec4 intensity[4];
  vec4 spot[4];
};
"""

RELIGHT_TYPEDEFS = """
struct PRTTRelight {
  vec4 light[%(n)d];
};
"""


def copy_variant() -> Variant:
    """The upload pass: a 2D texture's texels into a band of rows (from row
    ``row0``, the viewport's) of one layer of a 2D array texture."""
    return Variant(
        name="prtt_copy_layer", defines=(), typedefs="", vertex_in=((0, "VEC2", "pos"),), interface=(),
        samplers=((0, "FLOAT_2D", "layerTex"),), uniform_bufs=(), push_constants=(("INT", "row0"),),
        vertex_files=("prtt_relight_vert.glsl",), fragment_files=("prtt_copy_frag.glsl",))


def relight_variant(bands: int, glossy_bands: int, shared: bool = False) -> Variant:
    """The relight pass: one layer of a bounce texture (pack.pack_bounce
    layout) from a relightable operator (pack.pack_relight_operator) and the
    light (pack.relight_block); ``glossy_bands`` 0 when it has no glossy rows;
    ``shared``: its glossy rows stored once for all colours, tinted in the
    pass (define RELIGHT_SHARED; pack.relight_operator_layers(expand=False))."""
    k, k4 = sh_sizes(bands)
    kg = glossy_bands * glossy_bands
    defines = (("SH_K", str(k)), ("SH_K4", str(k4)), ("RELIGHT_KG", str(max(kg, 1))),
               ("RELIGHT_KG4", str(max((kg + 3) // 4, 1))))
    if shared and glossy_bands:
        defines += (("RELIGHT_SHARED", "1"),)
    return Variant(
        name=f"prtt_relight_b{bands}_g{glossy_bands}" + ("_shared" if shared and glossy_bands else ""),
        defines=defines, typedefs=RELIGHT_TYPEDEFS % {"n": 3 * k4},
        vertex_in=((0, "VEC2", "pos"),), interface=(), samplers=((0, "FLOAT_2D_ARRAY", "relightTex"),),
        uniform_bufs=((0, "PRTTRelight", "relight"),), push_constants=(("INT", "out_colour"), ("INT", "out_q")),
        vertex_files=("prtt_relight_vert.glsl",), fragment_files=("prtt_relight_frag.glsl",))
