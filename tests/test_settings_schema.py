"""One declaration of the bake settings (core/settings_schema.py) and the four
places generated from it: the core dataclasses, the bake-job command line, the
Blender command line and scene.prtt's properties, plus docs/format.md §5.

Each test compares one consumer with the schema as it *behaves* (registered
properties, parsed options, validate()), so a hand edit of any of them (a
default, a range, a help text, a new option or property) fails here."""
import argparse
import dataclasses
import os

import pytest

from prtt_addon.core import settings_schema as schema
from prtt_addon.core.bake.estimators.transfer import ADAPTIVE_TOL_LIMITS, INT_LIMITS, TransferSettings
from prtt_addon.core.bake.pipeline.context import BAKE_INT_LIMITS, BakeSettings

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
TYPES = {"int": "int", "float": "float", "bool": "bool", "choice": "str"}

#: Options of the command lines that are not bake settings (--dask: where the
#: bake runs, not what it makes; the outputs are the same bits).
BAKE_JOB_OTHER = {"-h", "--help", "--out", "--force", "--env", "--env-strength", "--env-rotation", "-q", "--quiet",
                  "--dask"}
BLENDER_OTHER = {"-h", "--help", "--out", "--absolute-out", "--scene", "--atlas", "--unwrap", "--force", "--job-only", "--no-save", "--save-as",
                 "-q", "--quiet", "--dask"}
#: scene.prtt properties that are not bake settings (layout, light, preview, state, where the bake runs).
SCENE_OTHER = {"unwrap_method", "existing_uv_map", "texture_sets", "output_dir", "selection_only", "light_source", "sky_sun", "hdri_sun",
               "builtin_environment", "preview", "preview_mode", "preview_bounces", "status", "progress",
               "baking", "last_bake", "dask_scheduler"}


def _outside(s):
    """Values just outside a numeric setting's range."""
    step = 1 if s.kind == "int" else 1e-3
    return s.lo - step, s.hi + step


# --- core ---------------------------------------------------------------------------------

def test_dataclasses_are_the_schema():
    assert [f.name for f in dataclasses.fields(TransferSettings)] == [s.name for s in schema.of_scope("transfer")]
    assert [f.name for f in dataclasses.fields(BakeSettings)] == [s.name for s in schema.core_settings()]
    d = BakeSettings()
    for f in dataclasses.fields(BakeSettings):
        s = schema.get(f.name)
        assert getattr(d, f.name) == s.default and type(getattr(d, f.name)).__name__ == TYPES[s.kind], f.name
        assert f.type == TYPES[s.kind], f.name
    d.validate()                                   # the defaults are valid


def test_validate_enforces_the_schema():
    for s in schema.core_settings():
        if s.kind in ("int", "float"):
            for ok in (s.lo, s.hi):
                BakeSettings(**{s.name: type(s.default)(ok)}).validate()
            for bad in _outside(s):
                bad = type(s.default)(bad)
                what = f"an integer {s.range_text()}" if s.kind == "int" else f"a number {s.lo:g}..{s.hi:g}"
                with pytest.raises(ValueError, match=f"^{s.name} must be {what}, got "):
                    BakeSettings(**{s.name: bad}).validate()
        elif s.kind == "choice":
            for v in s.values:
                BakeSettings(**{s.name: v}).validate()
            with pytest.raises(ValueError, match=f"^{s.name} must be one of {', '.join(s.values)}, got 'nope'"):
                BakeSettings(**{s.name: "nope"}).validate()
        else:
            for v in (True, False):
                if s.name in ("textures", "vertex_mode"):     # not both off (nothing to bake)
                    BakeSettings(textures=v, vertex_mode=not v).validate()
                else:
                    BakeSettings(**{s.name: v}).validate()
            with pytest.raises(ValueError, match=f"^{s.name} must be true or false, got 0"):
                BakeSettings(**{s.name: 0}).validate()


def test_derived_limits_and_shared_constants():
    from prtt_addon.core.bake.estimators import sampling
    from prtt_addon.core.model import scene
    from prtt_addon.core.preview.shader_source import MAX_PREVIEW_BANDS
    ints = {s.name: (s.lo, s.hi) for s in schema.core_settings() if s.kind == "int"}
    assert {k: v[:2] for k, v in {**INT_LIMITS, **BAKE_INT_LIMITS}.items()} == ints
    assert ADAPTIVE_TOL_LIMITS == (schema.get("adaptive_tol").lo, schema.get("adaptive_tol").hi)
    assert schema.MAX_RESOLUTION == scene.MAX_RESOLUTION == schema.get("resolution").hi
    assert schema.PREVIEW_MAX_BANDS == MAX_PREVIEW_BANDS
    # the estimators accept every value the schema offers, and refuse others
    for sampler in schema.get("sampler").values:
        for dist in schema.get("distribution").values:
            assert sampling.pattern_bank(1, 8, 2, sampler, dist, 1)[0].shape[-1] == 3
    with pytest.raises(ValueError):
        sampling.pattern_bank(1, 8, 2, "halton", "cosine", 1)


def test_schema_is_coherent():
    options = [o for s in schema.SETTINGS for o in s.options]
    assert len(options) == len(set(options)), "an option is declared twice"
    for s in schema.SETTINGS:
        assert s.help and s.help == s.help.strip() and not s.help.endswith("."), s.name
        assert s.scope in ("transfer", "bake", "job", "blender")
        if s.kind in ("int", "float"):
            assert s.lo <= s.default <= s.hi and s.option and s.metavar, s.name
        if s.kind == "bool":
            assert len(s.flags) == 2 and s.off_help, s.name
        if s.kind == "choice":
            assert s.default in s.values and s.option, s.name
        if s.ui is not None and s.kind in ("int", "float"):
            lo = s.ui.soft_lo if s.ui.soft_lo is not None else s.lo
            hi = s.ui.soft_hi if s.ui.soft_hi is not None else s.hi
            # soft limits narrow the hard range, never widen it
            assert s.lo <= lo <= hi <= s.hi, s.name
            if (s.ui.soft_lo, s.ui.soft_hi) != (None, None):
                assert s.ui.why_soft, f"{s.name}: say why the panel's slider stops short"
        if s.scope in ("job", "blender"):
            assert schema.has_ui(s), s.name


# --- command lines ----------------------------------------------------------------------------

def _options(parser):
    return {o: a for a in parser._actions for o in a.option_strings}


def _error(parser, argv, capsys):
    with pytest.raises(SystemExit) as e:
        parser.parse_args(argv)
    assert e.value.code == 2
    return capsys.readouterr().err.strip().splitlines()[-1]


def check_options(parser, settings, other, base, capsys, *, help_of=lambda s: s.help, defaults=()):
    """Every setting's options parse exactly its range and choices; nothing else is a setting."""
    opts = _options(parser)
    assert set(opts) - other == {o for s in settings for o in s.options}
    for s in settings:
        for o in s.options:
            a = opts[o]
            assert a.dest == s.name and a.default is None, o
        if s.kind == "bool":
            on, off = s.flags
            assert help_of(s) in opts[on].help and s.off_help in opts[off].help
            assert getattr(parser.parse_args(base + [on]), s.name) is True
            assert getattr(parser.parse_args(base + [off]), s.name) is False
            assert getattr(parser.parse_args(base), s.name) is None
            continue
        assert opts[s.option].help.startswith(help_of(s)), s.option
        if s.name in defaults:                  # the help says what applies without the option
            assert opts[s.option].help.endswith(f"; default {schema.format_number(s.default)})"), opts[s.option].help
        if s.kind == "choice":
            for v in s.values:
                for text in (v, v.upper(), v.title()):
                    assert getattr(parser.parse_args(base + [s.option, text]), s.name) == v
            assert _error(parser, base + [s.option, "nope"], capsys).endswith(
                f"error: {s.option} nope is an invalid choice: it must be one of {', '.join(s.values)}")
            continue
        assert f"({s.range_text()}" in opts[s.option].help, s.option
        for ok in (s.lo, s.hi):
            assert getattr(parser.parse_args(base + [s.option, str(ok)]), s.name) == ok
        for bad in _outside(s):
            text = str(type(s.default)(bad))
            assert _error(parser, base + [s.option, text], capsys).endswith(
                f"error: {s.option} {text} is out of range: it must be {s.range_text()}"), s.option


def _subparser(name):
    from prtt_addon.cli import build_parser
    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    return sub.choices[name]


def test_bake_job_options_are_the_schema(capsys):
    check_options(_subparser("bake-job"), schema.of_scope("job") + schema.core_settings(), BAKE_JOB_OTHER,
                  ["job.npz", "--out", "o"], capsys,
                  defaults={s.name for s in schema.core_settings() if s.kind in ("int", "float")})


@pytest.mark.blender
def test_blender_bake_options_are_the_schema(capsys):
    pytest.importorskip("bpy")
    from prtt_addon.blender.commands import bake_parser
    check_options(bake_parser("prtt bake"), list(schema.SETTINGS), BLENDER_OTHER, ["scene.blend"], capsys)


# --- Blender properties ------------------------------------------------------------------------

@pytest.mark.blender
def test_scene_properties_are_the_schema():
    from tests.blender_util import addon_bpy
    bpy = addon_bpy()
    rna = bpy.context.scene.prtt.bl_rna.properties
    props = schema.ui_properties()
    names = {p.identifier for p in rna if p.identifier not in ("rna_type", "name")}
    # every bake setting the panel holds comes from the schema; the rest is layout, light, preview, state
    assert names - {p.name for p in props} == SCENE_OTHER
    kinds = {"int": "INT", "float": "FLOAT", "bool": "BOOLEAN", "enum": "ENUM"}
    for p in props:
        r = rna[p.name]
        assert (r.type, r.name, r.description) == (kinds[p.kind], p.label, p.description), p.name
        if p.kind == "enum":
            assert [(i.identifier, i.name, i.description) for i in r.enum_items] == list(p.items)
            assert r.default == p.default
            continue
        assert r.default == pytest.approx(p.default, rel=1e-6), p.name
        if p.kind in ("int", "float"):
            assert (r.hard_min, r.hard_max) == pytest.approx((p.lo, p.hi)), p.name
            soft = (p.lo if p.soft_lo is None else p.soft_lo, p.hi if p.soft_hi is None else p.soft_hi)
            assert (r.soft_min, r.soft_max) == pytest.approx(soft), p.name
        if p.kind == "int":
            assert -2 ** 31 <= p.lo and p.hi < 2 ** 31, p.name          # Blender ints are 32-bit
    for s in schema.SETTINGS:                   # tooltips: the help, with the range and its unit
        if s.ui is not None and s.kind in ("int", "float"):
            d = rna[s.ui.prop].description
            assert d.lower().startswith(s.help.lower()) and f"{schema.format_number(s.lo)} to {schema.format_number(s.hi)}" in d
            assert s.unit in d, s.name
    ob = bpy.types.Object.bl_rna.properties["prtt"].fixed_type.properties["resolution"]
    assert (ob.hard_min, ob.hard_max) == (0, schema.MAX_RESOLUTION)


@pytest.mark.blender
def test_bake_settings_come_from_the_scene_through_the_schema():
    from tests.blender_util import addon_bpy
    bpy = addon_bpy()
    from prtt_addon.blender.bake.run import bake_settings
    st = bpy.context.scene.prtt
    assert bake_settings(bpy.context.scene).as_dict() == BakeSettings().as_dict()
    values = {"bands": 16, "rays": 1, "adaptive_tol": 0.25, "dilate": 64, "half": False, "normal_maps": False,
              "vertex_mode": True, "bounces": 0, "bounce_rays": 16384, "min_rays": 8, "seed": 9}
    props, once = schema.ui_from_values(values)
    assert props == {"bands": 16, "rays": 1, "adaptive": True, "adaptive_tolerance": 0.25, "dilate": 64,
                     "storage": "FLOAT", "normal_maps": False, "vertex_transfer": True, "bounces": 0,
                     "bounce_rays": 16384}
    assert once == {"min_rays": 8, "seed": 9}
    for k, v in props.items():
        setattr(st, k, v)
    got = bake_settings(bpy.context.scene).as_dict()
    assert got == {**BakeSettings().as_dict(), **{k: v for k, v in values.items() if k not in once}}
    st.adaptive = False
    assert bake_settings(bpy.context.scene).adaptive_tol == 0.0
    assert schema.ui_from_values({"adaptive_tol": 0.0})[0] == {"adaptive": False}
    assert schema.ui_from_values({"resolution": 64, "padding": 8})[0] == {"resolution": 64, "padding": 8}


# --- docs/format.md --------------------------------------------------------------------------

def test_format_md_table_is_generated():
    with open(os.path.join(ROOT, "docs", "format.md"), encoding="utf-8") as f:
        text = f.read()
    assert schema.doc_section(text) == schema.settings_table(), \
        "docs/format.md's settings table is stale: python -m prtt_addon.core.settings_schema --write"
    table = schema.settings_table()
    for s in schema.SETTINGS:                   # every setting has its row
        assert f"| `{s.name}` |" in table
