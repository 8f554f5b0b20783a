"""Compile the preview's shader variants with Blender's ``gpu`` module (cached)."""
from __future__ import annotations

import atexit

import gpu

from ...core.preview.shader_source import Variant, copy_variant, depth_variant, relight_variant, variant

_CACHE: dict = {}


def free_shaders() -> None:
    """Let the compiled shaders go (they are compiled again when next needed)."""
    _CACHE.clear()


# Shaders still held when Blender shuts its GPU module down crash the
# interpreter's exit (a segfault in its last garbage collection, seen after
# ``python -m prtt_addon render``): let them go first. atexit runs this before
# bpy's own exit handler, registered earlier.
atexit.register(free_shaders)


class ShaderError(RuntimeError):
    """A preview shader failed to compile; the message names the variant."""


def create_info(v: Variant):
    info = gpu.types.GPUShaderCreateInfo()
    for name, value in v.defines:
        info.define(name, value)
    if v.typedefs:
        info.typedef_source(v.typedefs)
    for slot, typ, name in v.vertex_in:
        info.vertex_in(slot, typ, name)
    if v.interface:
        iface = gpu.types.GPUStageInterfaceInfo(f"{v.name}_iface")
        for interp, typ, name in v.interface:
            getattr(iface, interp)(typ, name)
        info.vertex_out(iface)
    for slot, typ, name in v.samplers:
        info.sampler(slot, typ, name)
    for slot, struct, name in v.uniform_bufs:
        info.uniform_buf(slot, struct, name)
    for typ, name in v.push_constants:
        info.push_constant(typ, name)
    info.fragment_out(0, "VEC4", "FragColor")
    info.vertex_source(v.vertex_source())
    info.fragment_source(v.fragment_source())
    return info


def build(v: Variant):
    """The compiled GPUShader of a variant (compiled once per process)."""
    sh = _CACHE.get(v.name)
    if sh is None:
        try:
            sh = gpu.shader.create_from_info(create_info(v))
        except Exception as exc:   # Blender raises a bare Exception with the compiler log on stderr
            raise ShaderError(f"PRTT shader {v.name} failed to compile: {exc}") from exc
        _CACHE[v.name] = sh
    return sh


def surface_shader(mode: str, bands: int, bounce: bool, display: bool = False, sun: bool = False,
                   lamps: bool = False):
    return build(variant(mode, bands, bounce=bounce, display=display, sun=sun, lamps=lamps))


def depth_shader():
    return build(depth_variant())


def relight_shader(bands: int, glossy_bands: int, shared: bool = False):
    return build(relight_variant(bands, glossy_bands, shared))


def copy_shader():
    return build(copy_variant())
