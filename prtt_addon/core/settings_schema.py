"""Bake settings, each declared once: name, type, default, range, help, unit.

Everything else is generated from :data:`SETTINGS` (tests/test_settings_schema.py
checks that each of them still agrees with it):

* ``core.bake.estimators.transfer.TransferSettings`` / ``core.bake.pipeline.context.BakeSettings``: field
  defaults, ``validate()`` (types, ranges, choices) and the derived
  ``INT_LIMITS`` / ``BAKE_INT_LIMITS`` / ``ADAPTIVE_TOL_LIMITS``;
* the options of ``python -m prtt_addon bake-job`` (``cli.add_bake_options``);
* the options of ``blender -c prtt bake`` and ``python -m prtt_addon bake``
  (``blender/commands.bake_parser``, through the same ``cli_options.add_setting_options``);
* the bake properties of ``scene.prtt`` (``blender/ui/properties.py`` builds its
  annotations from :func:`ui_properties`), and ``blender/bake/run.bake_settings``
  (:func:`core_from_ui`);
* the settings table of docs/format.md §5 (:func:`settings_table`; rewrite it
  with ``python -m prtt_addon.core.settings_schema --write``).

Ranges. ``lo``..``hi`` is the one *hard* range of a setting: the core refuses
anything outside it, both command lines refuse it (exit 2, naming the option,
the value and the range), and the Blender property has it as its min/max, so
a value typed in the panel can never be one a job file would refuse. Where the
panel should steer the user to less (the preview draws up to 8 SH bands; a
slider up to 65536 rays is useless), the property gets *soft* limits
(``soft_lo``/``soft_hi``: the slider's range; typing still reaches the hard
range) and the help says why.

Scopes. ``transfer`` and ``bake`` settings are fields of TransferSettings and
BakeSettings (a job file's ``extra.settings``). ``job`` settings (resolution)
are options of both command lines but not a field: the bake-job option sets
every texture set's resolution, the Blender one the scene's. ``blender``
settings exist only in the add-on (the unwrap margin and texel density).

Blender forms that are not one property of the same type map explicitly
(:data:`UI_MAPPINGS`): ``half`` is the *Storage* enum (HALF = true, FLOAT =
false); ``adaptive_tol`` is the *Adaptive* switch plus *Tolerance* (off = 0).
Settings with ``ui=None`` have no property: the panel bakes with their
defaults, and ``blender -c prtt bake`` passes them for one bake only (they
are not stored in the .blend).

No bpy here: the add-on turns :class:`UiProp` into ``bpy.props`` calls.
"""
from __future__ import annotations

import dataclasses
import math
from typing import Any, Callable, Mapping

import numpy as np

#: The choices of settings whose code lives in the estimators (denoise.py,
#: sampling.py import them from here: the schema sits below the bake).
DENOISE_FILTERS = ("auto", "none", "edge-aware", "oidn")
SAMPLERS = ("sobol", "stratified", "random")
DISTRIBUTIONS = ("cosine", "uniform")

#: Bands the viewport preview can draw (== shader_source.MAX_PREVIEW_BANDS:
#: the TPFL matrix of 9 bands, 3 x 81 x 81 floats, exceeds a 64 KB uniform
#: block; tests check the two agree). Bakes may use up to 16.
PREVIEW_MAX_BANDS = 8
#: Texels a side of a texture set (== core.model.scene.MAX_RESOLUTION; tests check).
MAX_RESOLUTION = 16384


@dataclasses.dataclass(frozen=True)
class Choice:
    value: str          # the core value (job files, command lines; matched case-insensitively there)
    label: str          # the panel's label
    help: str


@dataclasses.dataclass(frozen=True)
class Ui:
    """How a setting appears in the panel (``scene.prtt.<prop>``)."""

    prop: str                       # property name (the panel reads it by name: never rename)
    label: str                      # property name shown in the UI
    soft_lo: float | None = None    # slider range (None: the hard limit)
    soft_hi: float | None = None
    why_soft: str = ""              # why the slider stops short of the hard range (in the tooltip)
    precision: int | None = None    # float properties: digits shown


@dataclasses.dataclass(frozen=True)
class Setting:
    name: str                       # core field (BakeSettings) or job/Blender-only name
    scope: str                      # "transfer" | "bake" | "job" | "blender"
    kind: str                       # "int" | "float" | "bool" | "choice"
    default: Any
    help: str                       # CLI help, property tooltip, docs (lower-case start, no full stop)
    unit: str = ""                  # of the value: "texels", "rays per texel", ...
    lo: float | None = None         # hard range, inclusive (int/float)
    hi: float | None = None
    choices: tuple = ()             # of Choice (kind "choice")
    flags: tuple = ()               # bool: (option that sets true, option that sets false)
    option: str | None = None       # int/float/choice: the command-line option
    metavar: str | None = None
    note: str = ""                  # why the hard range is what it is (docs only)
    ui: Ui | None = None            # scene.prtt property, if any (see UI_MAPPINGS for half, adaptive_tol)
    cli_default: str = ""           # what the commands bake with when the option is not given (docs)
    off_help: str = ""              # bool: help of the option that sets false

    @property
    def options(self) -> tuple:
        """Every command-line option of this setting."""
        return self.flags if self.kind == "bool" else ((self.option,) if self.option else ())

    @property
    def values(self) -> tuple:
        return tuple(c.value for c in self.choices)

    def range_text(self) -> str:
        """``lo..hi`` as the command lines say it (exact values)."""
        return f"{format_number(self.lo)}..{format_number(self.hi)}"

    def check(self, value) -> None:
        """Raise ValueError "name must be ..., got ..." unless ``value`` is valid
        (strict types: no bool for an int, no 64.0 for an int, no "no" for a flag)."""
        if self.kind == "int":
            check_int(self.name, value, self.lo, self.hi)
        elif self.kind == "float":
            check_number(self.name, value, self.lo, self.hi)
        elif self.kind == "bool":
            check_flag(self.name, value)
        elif self.kind == "choice":
            check_choice(self.name, value, self.values)


def check_int(name: str, value, lo: int, hi: int) -> None:
    """Raise ValueError unless ``value`` is an integer (not a bool) in lo..hi."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)) \
            or not lo <= value <= hi:
        raise ValueError(f"{name} must be an integer {lo}..{hi}, got {value!r}")


def check_number(name: str, value, lo: float, hi: float) -> None:
    """Raise ValueError unless ``value`` is a finite number (not a bool) in lo..hi."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.integer, np.floating)) \
            or not (math.isfinite(value) and lo <= value <= hi):
        raise ValueError(f"{name} must be a number {lo:g}..{hi:g}, got {value!r}")


def check_choice(name: str, value, choices) -> None:
    if not isinstance(value, str) or value not in choices:
        raise ValueError(f"{name} must be one of {', '.join(choices)}, got {value!r}")


def check_flag(name: str, value) -> None:
    if not isinstance(value, (bool, np.bool_)):
        raise ValueError(f"{name} must be true or false, got {value!r}")


def format_number(v) -> str:
    if isinstance(v, float) and not v.is_integer():
        return f"{v:g}"
    return str(int(v)) if isinstance(v, float) else str(v)


def _choices(values: tuple, described: dict) -> tuple:
    """Choice entries for ``values`` (declared where they are implemented), one
    (label, help) each: a value without one, or one too many, fails at import."""
    if set(values) != set(described):
        raise RuntimeError(f"settings schema: choices {sorted(described)} do not match {sorted(values)}")
    return tuple(Choice(v, *described[v]) for v in values)


ESTIMATORS = ("balanced", "control-variate", "plain")
#: Per-set tuning (core/bake/pipeline/bounce_stage.py applies "auto").
TUNINGS = ("fixed", "auto")
#: What the bounce textures hold (core/bake/pipeline/relightable_stage.py bakes "relightable").
BOUNCE_MODES = ("baked", "relightable")

SETTINGS: tuple[Setting, ...] = (
    # --- transfer (TransferSettings) ----------------------------------------------------
    Setting("bands", "transfer", "int", 5, "spherical-harmonic bands: bands² coefficients a texel, "
            "5 = 25 as in the paper", unit="bands", lo=1, hi=16, option="--bands", metavar="N",
            note="16 bands = 256 coefficients a texel",
            ui=Ui("bands", "SH Bands", soft_hi=PREVIEW_MAX_BANDS,
                  why_soft=f"the viewport preview draws up to {PREVIEW_MAX_BANDS} bands")),
    Setting("rays", "transfer", "int", 256, "rays per texel; the maximum when adaptive", unit="rays",
            lo=1, hi=1 << 16, option="--rays", metavar="N",
            ui=Ui("rays", "Rays", soft_lo=16, soft_hi=4096,
                  why_soft="below 16 rays noise dominates; 4096 are close to converged")),
    Setting("sampler", "transfer", "choice", "sobol", "ray pattern of each texel",
            choices=_choices(SAMPLERS, {"sobol": ("Sobol'", "Owen-scrambled Sobol' points"),
                                        "stratified": ("Stratified", "jittered strata"),
                                        "random": ("Random", "independent uniform points")}),
            option="--sampler"),
    Setting("distribution", "transfer", "choice", "cosine", "how ray directions are distributed",
            choices=_choices(DISTRIBUTIONS, {"cosine": ("Cosine", "cosine-weighted (importance) hemisphere"),
                                             "uniform": ("Uniform", "uniform hemisphere")}),
            option="--distribution"),
    Setting("estimator", "transfer", "choice", "balanced", "how a texel's rays become coefficients, see "
            "docs/bake.md",
            choices=_choices(ESTIMATORS, {
                "balanced": ("Balanced", "weights that integrate the unoccluded transfer exactly"),
                "control-variate": ("Control Variate", "exact for fully visible texels"),
                "plain": ("Plain", "the textbook Monte Carlo mean")}),
            option="--estimator"),
    Setting("adaptive_tol", "transfer", "float", 0.0, "> 0: stop a texel once the RMS standard error of its "
            "coefficients is below this; 0 = every texel traces all its rays", lo=0.0, hi=100.0,
            option="--adaptive", metavar="TOL",
            note="above ~2 every texel stops after its first round (coefficients are below √π)"),
    Setting("min_rays", "transfer", "int", 64, "rays of the first adaptive round; each later round "
            "doubles the total, up to the rays", unit="rays", lo=1, hi=1 << 16, option="--min-rays", metavar="N"),
    Setting("analytic", "transfer", "bool", True, "zero-ray path for texels that provably see no geometry",
            flags=("--analytic", "--no-analytic"), off_help="trace provably unoccluded texels too"),
    Setting("guiding", "transfer", "bool", True, "aim seven in eight of a texel's rays at the openings its "
            "neighbourhood sees the sky through (learned from 16 pilot rays of one texel in four), where at most "
            "one in ten of its rays would escape: a room lit through a window without blotches; texels of open or "
            "closed neighbourhoods are baked as without it", flags=("--guiding", "--no-guiding"),
            off_help="every texel's rays cosine-distributed (the bakes before guiding, byte for byte)",
            ui=Ui("guiding", "Guide Rays to Openings")),
    Setting("seed", "transfer", "int", 0, "all randomness derives from it", lo=0, hi=(1 << 32) - 1,
            option="--seed", metavar="N", note="hashes use 32 bits: larger seeds would repeat smaller ones"),
    Setting("threads", "transfer", "int", 0, "worker threads; 0 = all cores", unit="threads", lo=0, hi=256,
            option="--threads", metavar="N", note="more threads than this is a typo, not a machine"),
    Setting("n_patterns", "transfer", "int", 64, "ray patterns neighbouring texels cycle through",
            unit="patterns", lo=1, hi=1024, option="--patterns", metavar="N",
            note="tables are built one by one (~1.4 ms each at 256 rays): 1024 take ~1.5 s, 8 s with "
                 "adaptive prefixes"),
    Setting("chunk_rays", "transfer", "int", 1 << 19, "rays per Embree call and thread", unit="rays",
            lo=1 << 10, hi=1 << 22, option="--chunk-rays", metavar="N",
            note="~66 B a ray in flight: 1024 keeps Embree calls efficient, 2^22 keeps a thread's buffers "
                 "under ~280 MB"),
    # --- bake (BakeSettings) ------------------------------------------------------------
    Setting("dilate", "bake", "int", 3, "rings of texels filled around each UV island", unit="texels",
            lo=0, hi=64, option="--dilate", metavar="N",
            note="in texels of the island's texture set", ui=Ui("dilate", "Dilation", soft_hi=16,
                                                                   why_soft="a few texels cover bilinear "
                                                                            "and mip lookups")),
    Setting("sun_detail", "bake", "int", 1, "texels of a sun's shadow mask per texel of its set, per side: 2 "
            "or 4 resolve penumbrae narrower than a texel (a 0.5 degree sun's are millimetres wide) at 4 or 16 "
            "times the mask's bytes (its rays grow with its penumbrae: sun_refine); the transfer is unchanged "
            "(a new value bakes the masks alone)",
            unit="x", lo=1, hi=4, option="--sun-detail", metavar="F",
            ui=Ui("sun_detail", "Sun Shadow Detail")),
    Setting("sun_refine", "bake", "bool", True, "a sun mask's texel traces its disc's first 4 rays, and "
            "all 64 only where they disagree or a texel within 2 of it has (a penumbra): the mask at a sixth "
            "of the rays or less (bench sun, 0.5 degrees: 1.86 s -> 0.26 s at Sun Shadow Detail 1, 7.5 s -> 0.9 s at 2), the same "
            "error against Cycles", flags=("--sun-refine", "--no-sun-refine"),
            off_help="every mask texel traces all its rays (the masks before it, byte for byte)"),
    Setting("sun_edges", "bake", "bool", True, "a sharp sun's shadow edges at their sub-texel place: "
            "beside the mask, each texel within 3 of an edge stores its distance to the edge's line and the "
            "penumbra's half-width (<set>.sun_edge.exr), and the preview draws the edge there, as sharp as "
            "the disc makes it; penumbrae a texel wide or wider are left to the mask",
            flags=("--sun-edges", "--no-sun-edges"),
            off_help="the mask alone (the files and keys before it, byte for byte)"),
    Setting("half", "bake", "bool", True, "half-float EXR textures (float32 for a texture whose values "
            "exceed 65504)", flags=("--half", "--float"), off_help="float32 EXR textures"),
    Setting("mips", "bake", "bool", False, "also write coverage-weighted mip levels", flags=("--mips", "--no-mips"),
            off_help="no mip levels"),
    Setting("texel_validity", "bake", "bool", True, "drop the texels whose sample point lies inside "
            "geometry or on another surface (nine in ten of 16 rays hit back faces or anything within half a "
            "texel: a floor under a box resting on it, a wall's foot on the floor's plane) and fill them from "
            "their valid neighbours by the dilation, so no dark crease shows where objects touch (the bounce "
            "textures keep them as traced); beside a wall of a single plane standing on a surface, that "
            "surface's texels take the wall's darker side's light (no bright leak into a room)",
            flags=("--texel-validity", "--no-texel-validity"),
            off_help="keep every texel as traced (the bakes before it, byte for byte, with --no-guided-filter)",
            ui=Ui("texel_validity", "Fill Texels Inside Geometry")),
    Setting("guided_filter", "bake", "bool", True, "smooth the transfer of the texels that guided rays "
            "baked (a room lit through a window) with a 5 x 5 joint bilateral filter on the same surface, "
            "guided by world position and normal; other texels keep their rows",
            flags=("--guided-filter", "--no-guided-filter"),
            off_help="the guided texels as traced (the bakes before it, byte for byte)",
            ui=Ui("guided_filter", "Smooth Guided Texels")),
    Setting("normal_maps", "bake", "bool", True, "shade with the scene's tangent-space normal maps",
            flags=("--normal-maps", "--no-normal-maps"), off_help="ignore normal maps",
            ui=Ui("normal_maps", "Normal Maps")),
    Setting("vertex_mode", "bake", "bool", False, "also bake per-vertex transfer (the preview's "
            "vertex baselines)", flags=("--vertex", "--no-vertex"), off_help="no per-vertex transfer",
            ui=Ui("vertex_transfer", "Vertex Transfer")),
    Setting("textures", "bake", "bool", True, "bake the transfer textures; off: per-vertex transfer only, "
            "with vertex mode", flags=("--textures", "--no-textures"),
            off_help="per-vertex transfer only (with --vertex)"),
    Setting("overlap", "bake", "choice", "warn", "what overlapping UV islands do",
            choices=(Choice("warn", "Warn", "bake with a warning"), Choice("error", "Error", "refuse to bake")),
            option="--overlap"),
    Setting("bounces", "bake", "int", 1, "inter-reflection levels: summed into one texture per set that "
            "the current light is applied to (bounce mode relightable), or a texture per level with the "
            "light baked in (baked: skipped with a warning when there is no light); 0 = off",
            unit="levels", lo=0, hi=8, option="--bounces", metavar="N", ui=Ui("bounces", "Bounces", soft_hi=3,
                                                                                why_soft="each level adds "
                                                                                         "less light")),
    Setting("bounce_rays", "bake", "int", 64, "rays per texel per bounce level", unit="rays", lo=1, hi=1 << 14,
            option="--bounce-rays", metavar="N", ui=Ui("bounce_rays", "Bounce Rays", soft_hi=1024,
                                                       why_soft="bounce light is smooth")),
    Setting("bounce_tolerance", "bake", "float", 0.005, "stop adding bounce levels once one carries less than "
            "this fraction of the direct light's energy (the sum of DC terms); 0 = bake every level",
            unit="of the direct light", lo=0.0, hi=1.0, option="--bounce-tolerance", metavar="F",
            note="each level carries at most the surfaces' albedo times the previous one",
            ui=Ui("bounce_tolerance", "Bounce Tolerance", soft_hi=0.1, why_soft="above 10 % levels that "
                  "visibly light the scene stop", precision=4)),
    Setting("bounce_denoise", "bake", "choice", "none", "filter each bounce level in texture space "
            "(off by default: on the run-time curve it does not pay, docs/benchmarks.md)",
            choices=_choices(DENOISE_FILTERS, {
                "auto": ("Auto", "edge-aware below 128 bounce rays (where it lowers the error at equal rays), "
                         "none from there on"),
                "none": ("None", "the bounce textures as traced"),
                "edge-aware": ("Edge-Aware", "joint bilateral within UV islands, guided by positions and normals"),
                "oidn": ("OIDN", "Intel Open Image Denoise on normalised SH (needs the optional pyoidn)")}),
            option="--bounce-denoise"),
    Setting("bounce_downscale", "bake", "int", 1, "bake and store the bounce textures at 1/N of each set's "
            "resolution per side (indirect light varies slowly; N x N fewer rays and bytes); a set whose "
            "resolution N does not divide, or whose UV islands would share texels at 1/N, keeps a finer grid "
            "(the manifest says which and why); 1 = the transfer's resolution", unit="per side", lo=1, hi=8,
            option="--bounce-downscale", metavar="N",
            note="UV margins are laid out in the transfer's texels: at 1/8 a 4-texel margin is half a texel",
            ui=Ui("bounce_downscale", "Bounce Downscale", soft_hi=4,
                  why_soft="the default 4-texel margins keep islands apart down to 1/2 (1/4 where islands "
                           "lie farther apart)")),
    Setting("tuning", "bake", "choice", "auto", "what each texture set gets: the same settings for all "
            "(fixed), or per set only what its shading needs (auto: bounce textures on a coarser grid where "
            "no UV islands mix, and with only the bands its materials read); the manifest records every "
            "choice and why",
            choices=_choices(TUNINGS, {
                "fixed": ("Fixed", "every set as the settings say (the bake before per-set tuning, byte for byte)"),
                "auto": ("Auto", "per set: bounce grid 1/2 where UV islands allow, bounce bands from the "
                         "materials (1 without glossy ones)")}),
            option="--tuning", ui=Ui("tuning", "Tuning")),
    Setting("bounce_mode", "bake", "choice", "relightable", "what the bounce textures hold: the inter-reflected "
            "light of the bake's light (baked: one texture per level, stale when the World changes), or "
            "a linear map of the light summed over all levels (relightable: the viewport and render apply "
            "the World as it is now; diffuse exactly, glossy lobes read bands 0-2 of the bounce light "
            "from bands 0-2 of the light)",
            choices=_choices(BOUNCE_MODES, {
                "baked": ("Baked", "bounce light under the bake's light, a texture per level (the paper's)"),
                "relightable": ("Relightable", "bounce light as a map of the light: turn or swap the World "
                                "without a rebake")}),
            option="--bounce-mode", ui=Ui("bounce_mode", "Bounce Mode")),
    # --- job (both command lines; not a BakeSettings field) -----------------------------
    Setting("resolution", "job", "int", 1024, "texels per side of each texture set: an atlas's, or under "
            "tuning fixed every set's; under tuning auto the largest an object's own set gets (sized from its "
            "surface area, 128 texels a metre; the bake prints each set's)", unit="texels",
            lo=1, hi=MAX_RESOLUTION, option="--resolution", metavar="N",
            note="a 16384² × 25 float32 texture is 27 GB",
            cli_default="bake-job: each set's own; Blender: the scene's (objects' overrides and texel density "
                        "still apply)",
            ui=Ui("resolution", "Resolution", soft_lo=8, soft_hi=8192,
                  why_soft="below 8 texels islands have no room for their margins; 8192² and more need "
                           "several GB")),
    # --- Blender only ---------------------------------------------------------------------
    Setting("padding", "blender", "int", 4, "space the unwrap leaves between UV islands, in texels of "
            "each object's own resolution (its override or texel density, else the scene's; the atlas's for "
            "One Atlas); at least 2, at least the dilation, and at least 3 x the bounce grid's downscale the "
            "bake will ask for (tuning auto: 6), so that the coarse bounce grid mixes no islands (measured on "
            "the UV map for each unwrap method: docs/addon.md, Unwrap)",
            unit="texels", lo=0, hi=64,
            option="--margin", metavar="N", ui=Ui("padding", "Margin (texels)", soft_hi=16,
                                                  why_soft="a few texels keep islands apart")),
    Setting("texel_density", "blender", "float", 0.0, "texels per metre: > 0 sizes each object's texture "
            "from its surface area (a power of two, up to the scene resolution); 0 = the scene resolution",
            unit="texels per metre", lo=0.0, hi=1e6, option="--texel-density", metavar="T",
            note="10^6 texels a metre is a 1 µm texel",
            ui=Ui("texel_density", "Texel Density", soft_hi=2048.0,
                  why_soft="2048 texels a metre is a half-millimetre texel")),
)

BY_NAME: dict[str, Setting] = {s.name: s for s in SETTINGS}


def get(name: str) -> Setting:
    return BY_NAME[name]


def of_scope(*scopes: str) -> list[Setting]:
    return [s for s in SETTINGS if s.scope in scopes]


def core_settings() -> list[Setting]:
    """BakeSettings' fields, in order (TransferSettings' first)."""
    return of_scope("transfer", "bake")


def default(name: str):
    """The default of a setting (dataclass field defaults use this)."""
    return BY_NAME[name].default


def int_limits(*scopes: str) -> dict:
    """{name: (lo, hi, why)} of the integer settings of ``scopes``."""
    return {s.name: (s.lo, s.hi, s.note or s.help) for s in of_scope(*scopes) if s.kind == "int"}


def validate(obj, scope: str) -> None:
    """Check every field of ``scope`` on ``obj`` (ValueError "name must be ..., got ...")."""
    for s in of_scope(scope):
        s.check(getattr(obj, s.name))


# --- Blender properties ------------------------------------------------------------------

@dataclasses.dataclass(frozen=True)
class UiProp:
    """One ``scene.prtt`` property, in bpy-free terms (blender/ui/properties.py turns
    it into IntProperty/FloatProperty/BoolProperty/EnumProperty)."""

    name: str
    kind: str                       # "int" | "float" | "bool" | "enum"
    label: str
    description: str
    default: Any
    lo: float | None = None
    hi: float | None = None
    soft_lo: float | None = None
    soft_hi: float | None = None
    items: tuple = ()               # enum: (identifier, label, description)
    precision: int | None = None
    setting: str = ""               # the schema setting it comes from


def _sentence(text: str) -> str:
    return text[:1].upper() + text[1:]


def describe(s: Setting, *, ui: Ui | None = None) -> str:
    """The tooltip: help, hard range with unit, and why the slider stops short."""
    text = _sentence(s.help)
    if s.kind in ("int", "float"):
        text += f" ({format_number(s.lo)} to {format_number(s.hi)}{' ' + s.unit if s.unit else ''}"
        why = ui.why_soft if ui is not None else ""
        text += f"; the slider stops at {_slider(ui)}: {why})" if why else ")"
    return text


def _slider(ui: Ui) -> str:
    parts = []
    if ui.soft_lo is not None:
        parts.append(format_number(ui.soft_lo))
    if ui.soft_hi is not None:
        parts.append(format_number(ui.soft_hi))
    return " and ".join(parts)


#: Settings whose Blender form is not one property of the same type. Each entry:
#: the properties it makes, to_core(get) -> the core value, from_core(value) ->
#: {property: value}.
def _half_props() -> list[UiProp]:
    s = BY_NAME["half"]
    return [UiProp("storage", "enum", "Storage", "Precision of the EXR textures", "HALF",
                   items=(("HALF", "Half", _sentence(s.help)),
                          ("FLOAT", "Float", "32-bit float EXR")), setting="half")]


def _adaptive_props() -> list[UiProp]:
    s = BY_NAME["adaptive_tol"]
    return [UiProp("adaptive", "bool", "Adaptive", "Stop each texel once its estimate is precise enough "
                   "(off: every texel traces all its rays)", False, setting="adaptive_tol"),
            UiProp("adaptive_tolerance", "float", "Tolerance",
                   f"While Adaptive is on: stop a texel once the RMS standard error of its coefficients is "
                   f"below this ({format_number(s.lo)} to {format_number(s.hi)}; the slider stops at 1e-05 and 1: "
                   f"above ~2 every texel stops after its first round)",
                   0.005, lo=s.lo, hi=s.hi, soft_lo=1e-5, soft_hi=1.0, precision=4, setting="adaptive_tol")]


UI_MAPPINGS: dict[str, dict[str, Callable]] = {
    "half": {
        "props": _half_props,
        "to_core": lambda get: get("storage") == "HALF",
        "from_core": lambda v: {"storage": "HALF" if v else "FLOAT"},
    },
    "adaptive_tol": {
        "props": _adaptive_props,
        "to_core": lambda get: float(get("adaptive_tolerance")) if get("adaptive") else 0.0,
        "from_core": lambda v: {"adaptive": v > 0, **({"adaptive_tolerance": float(v)} if v > 0 else {})},
    },
}


def ui_properties() -> list[UiProp]:
    """Every scene.prtt property that holds a schema setting, in schema order."""
    props = []
    for s in SETTINGS:
        if s.name in UI_MAPPINGS:
            props.extend(UI_MAPPINGS[s.name]["props"]())
        elif s.ui is not None:
            kind = "enum" if s.kind == "choice" else s.kind
            items = tuple((c.value.upper(), c.label, c.help) for c in s.choices)
            props.append(UiProp(s.ui.prop, kind, s.ui.label, describe(s, ui=s.ui),
                                s.default.upper() if kind == "enum" else s.default,
                                lo=s.lo, hi=s.hi, soft_lo=s.ui.soft_lo, soft_hi=s.ui.soft_hi, items=items,
                                precision=s.ui.precision, setting=s.name))
    return props


def has_ui(s: Setting) -> bool:
    return s.name in UI_MAPPINGS or s.ui is not None


def core_from_ui(get: Callable[[str], Any]) -> dict:
    """The core settings the panel holds, from ``get(property name)`` (e.g.
    ``lambda n: getattr(scene.prtt, n)``); the others keep their defaults."""
    out = {}
    for s in core_settings():
        if s.name in UI_MAPPINGS:
            out[s.name] = UI_MAPPINGS[s.name]["to_core"](get)
        elif s.ui is not None:
            v = get(s.ui.prop)
            if s.kind == "float":
                # Blender stores float properties in single precision: take the
                # shortest decimal that rounds to it (0.005, not 0.004999999888).
                v = float(str(np.float32(v)))
            out[s.name] = v.lower() if s.kind == "choice" else v
    return out


def ui_from_values(values: Mapping[str, Any]) -> tuple[dict, dict]:
    """Split settings (e.g. parsed options) into (scene.prtt property values,
    core overrides without a property: for one bake only)."""
    props, overrides = {}, {}
    for name, v in values.items():
        s = BY_NAME[name]
        if name in UI_MAPPINGS:
            props.update(UI_MAPPINGS[name]["from_core"](v))
        elif s.ui is not None:
            props[s.ui.prop] = v.upper() if s.kind == "choice" else v
        elif s.scope in ("transfer", "bake"):
            overrides[name] = v
        else:
            raise ValueError(f"setting {name!r} has no place in Blender")
    return props, overrides


# --- docs/format.md ------------------------------------------------------------------------

TABLE_BEGIN = "<!-- settings table: generated from prtt_addon/core/settings_schema.py by " \
              "`python -m prtt_addon.core.settings_schema --write`; do not edit by hand -->"
TABLE_END = "<!-- end of the generated settings table -->"


def _doc_num(v) -> str:
    """Numbers as the docs write them: 2^19, 2^32 − 1, 10^6."""
    if isinstance(v, float) and not v.is_integer():
        return f"{v:g}"
    v = int(v)
    if v == (1 << 32) - 1:
        return "2^32 − 1"
    if v > 1 << 16 and v & (v - 1) == 0:
        return f"2^{v.bit_length() - 1}"
    if v >= 10 ** 6 and str(v).rstrip("0") == "1":
        return f"10^{len(str(v)) - 1}"
    return str(v)


def _doc_default(s: Setting) -> str:
    if s.kind == "bool":
        return "true" if s.default else "false"
    if s.kind == "choice":
        return f"`{s.default}`"
    return _doc_num(s.default)


def _doc_range(s: Setting) -> str:
    if s.kind in ("int", "float"):
        return f"{_doc_num(s.lo)} … {_doc_num(s.hi)}" + (f" {s.unit}" if s.unit else "")
    if s.kind == "choice":
        return ", ".join(f"`{v}`" for v in s.values)
    return "true, false"


def _doc_options(s: Setting) -> str:
    if s.kind == "bool":
        return " / ".join(f"`{f}`" for f in s.flags)
    if s.kind == "choice":
        return f"`{s.option} {'|'.join(s.values)}`"
    return f"`{s.option} {s.metavar}`" if s.option else "—"


def _doc_blender(s: Setting) -> str:
    if s.name == "half":
        return "*Storage* (`storage`): Half = true, Float = false"
    if s.name == "adaptive_tol":
        return ("*Adaptive* (`adaptive`) on: *Tolerance* (`adaptive_tolerance`, default 0.005, "
                "slider 1e-05 … 1); off: 0")
    if s.ui is None:
        return "—"
    text = f"*{s.ui.label}* (`{s.ui.prop}`)"
    if s.ui.soft_lo is not None or s.ui.soft_hi is not None:
        lo = s.ui.soft_lo if s.ui.soft_lo is not None else s.lo
        hi = s.ui.soft_hi if s.ui.soft_hi is not None else s.hi
        text += f", slider {_doc_num(lo)} … {_doc_num(hi)}"
        if s.ui.why_soft:
            text += f": {s.ui.why_soft}"
    return text


def _doc_meaning(s: Setting) -> str:
    text = s.help
    if s.kind == "choice":
        text += ": " + "; ".join(f"`{c.value}` {c.help}" for c in s.choices)
    if s.note:
        text += f"; {s.note}"
    if s.cli_default:
        text += f"; without the option: {s.cli_default}"
    return text


def settings_table() -> str:
    """The markdown of docs/format.md §5's table (between TABLE_BEGIN and TABLE_END)."""
    head = ("| setting | default | range | command-line option | Blender (`scene.prtt`) | meaning |\n"
            "|---|---|---|---|---|---|\n")
    groups = (("transfer", "bake"), ("job",), ("blender",))
    titles = {("job",): "*job (both command lines; Blender: the scene's)*",
              ("blender",): "*Blender only (unwrap; `blender -c prtt bake` options)*"}
    rows = []
    for g in groups:
        if g in titles:
            rows.append(f"| {titles[g]} | | | | | |")
        for s in of_scope(*g):
            cells = (f"`{s.name}`", _doc_default(s), _doc_range(s), _doc_options(s), _doc_blender(s),
                     _doc_meaning(s))
            rows.append("| " + " | ".join(c.replace("|", "\\|") for c in cells) + " |")
    return f"{TABLE_BEGIN}\n{head}" + "\n".join(rows) + f"\n{TABLE_END}"


def doc_section(text: str) -> str:
    """The generated table as it stands in ``text`` (docs/format.md), markers included."""
    a = text.index(TABLE_BEGIN)
    b = text.index(TABLE_END, a) + len(TABLE_END)
    return text[a:b]


def write_table(path: str) -> bool:
    """Put the generated table into ``path`` (between the markers); True if it changed."""
    with open(path, encoding="utf-8") as f:
        text = f.read()
    new = text.replace(doc_section(text), settings_table())
    if new == text:
        return False
    with open(path, "w", encoding="utf-8") as f:
        f.write(new)
    return True


def main(argv=None) -> int:
    import argparse
    import os
    p = argparse.ArgumentParser(prog="python -m prtt_addon.core.settings_schema",
                                description="Print the bake settings table of docs/format.md, or rewrite it there.")
    p.add_argument("--write", action="store_true", help="rewrite the table in docs/format.md")
    p.add_argument("--doc", default=os.path.join(os.path.dirname(__file__), "..", "..", "docs", "format.md"),
                   help="the markdown file (default: docs/format.md)")
    args = p.parse_args(argv)
    if args.write:
        print(("rewrote the table in " if write_table(args.doc) else "up to date: ") + os.path.normpath(args.doc))
    else:
        print(settings_table())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
