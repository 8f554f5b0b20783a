"""Draw a PreviewScene with Blender's ``gpu`` module: viewport and offscreen.

One :class:`Renderer` owns every GPU resource (textures, vertex/index
buffers, uniform blocks), created lazily from the scene's arrays and cached by
key; whatever a frame did not use is freed at the end of the frame, so
resources go away with the objects and textures they belonged to.

A frame (``Renderer.draw``):

1. per-fragment modes: a depth pre-pass of every mesh (colour writes off),
   then the shading pass with depth test LESS_EQUAL and depth writes off, so
   each visible pixel runs the expensive shader once (the paper's early depth);
2. per mesh: its set's transfer (and summed bounce) texture, per material
   range its uniform block and textures.

The caller sets up the framebuffer (the viewport's, or an offscreen one in
:func:`render_offscreen`).

An object that cannot be drawn (no per-vertex transfer in a vertex mode, a
texture that cannot be read or uploaded) is left out of the frame and listed
in ``FrameStats.skipped`` with the reason and the remedy: the viewport keeps
drawing the rest, while offscreen renders (preview_render) ask
:meth:`Renderer.prepare` first and refuse to make a partial image.
"""
from __future__ import annotations

import dataclasses
import hashlib
import os
import zipfile

import gpu
import numpy as np
from gpu_extras.batch import batch_for_shader

from ...core.base.memory import GiB, MemoryLimitError, check_fits
from ...core.io.exr_io import TextureError, texture_header
from ...core.preview import pack as pp
from ...core.preview.shader_source import FRAGMENT_MODES, GAUNT_WIDTH, MODES, VERTEX_MODES
from ..versions import layer_slot
from . import shaders as gpu_shaders


def _buffer(a: np.ndarray):
    a = np.ascontiguousarray(a, dtype=np.float32).ravel()
    return gpu.types.Buffer("FLOAT", a.size, a)


def _digest(*arrays) -> str:
    h = hashlib.sha1()
    for a in arrays:
        h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()


def _matrix(M: np.ndarray):
    import mathutils
    return mathutils.Matrix(np.asarray(M, np.float64).tolist())


#: The largest share of available memory the preview's textures may take (as the bake's check).
MEMORY_FRACTION = 0.8
#: What to do when a set's textures do not fit.
MEMORY_ADVICE = ("bake at a lower resolution or with a larger Bounce Downscale, hide the objects of other "
                 "texture sets, or close what else holds memory")

#: Why an object is left out of a vertex-mode frame, with what to do about it.
NO_VERTEX_TRANSFER = ("the bake has no per-vertex transfer: bake again with Vertex Transfer on "
                      "(PRTT › Bake › Output › Vertex Transfer)")
STALE_VERTEX_TRANSFER = ("its per-vertex transfer does not match its mesh (edited since the bake?): "
                         "bake again")


class TextureUploadError(ValueError):
    """A baked texture cannot be used: unreadable, the wrong shape, or beyond the
    GPU's limits. The message names the file."""


@dataclasses.dataclass
class FrameStats:
    drawn: list = dataclasses.field(default_factory=list)
    skipped: dict = dataclasses.field(default_factory=dict)   # mesh name -> reason
    triangles: int = 0
    texture_bytes: int = 0          # the baked textures on the GPU (transfer, bounce, vertex, relight operator)
    base_bytes: int = 0             # an offscreen render's RSS before its textures (offscreen.check_memory)
    estimate_bytes: int = 0         # and its estimated peak RSS


class Renderer:
    """GPU resources and drawing for the preview (one per viewport/offscreen user)."""

    def __init__(self):
        self._res: dict = {}
        self._stamp: dict = {}      # key -> frame number of its last use
        self._frame = 0
        self._view_ubo = None

    # --- resources ------------------------------------------------------------------
    def _get(self, key, make):
        self._stamp[key] = self._frame
        r = self._res.get(key)
        if r is None:
            r = self._res[key] = make()
        return r

    def _array_texture(self, packed: np.ndarray, path: str = "texture"):
        """(L, H, W, 4) -> RGBA 2D array texture, half when that changes no value.

        Raises TextureUploadError naming ``path`` when the GPU cannot hold it:
        checked against the GL limits first, since drivers answer an oversized
        texture with an anonymous allocation failure."""
        L, H, W, _ = packed.shape
        _check_limits(path, W, H, L)
        fmt = "RGBA16F" if pp.half_exact(packed) else "RGBA32F"
        return _new_layered(path, W, H, L, fmt, _buffer(packed)), packed.size * (2 if fmt == "RGBA16F" else 4)

    def _layer_texture(self, src):
        """A LayerSource (or LevelSumSource) as an RGBA 2D array texture, uploaded a band of rows
        of a layer at a time: each band of the file's channels (decoded in a
        child, exr_bands) is staged layer by layer into a float32 buffer of
        that band, goes up as a 2D texture and is drawn into its rows of its
        layer (shaders/prtt_copy_frag.glsl, texel for texel), so the CPU holds
        one band (pack.STAGING_BYTES), never the texture. Half when that
        changes no value (known from the file's types, else checked band by
        band first). Returns (GPUTexture, bytes) as :meth:`_array_texture`."""
        L, H, W = src.layers, src.height, src.width
        _check_limits(src.path, W, H, L)
        rows = src.band_rows()
        stage = gpu.types.Buffer("FLOAT", rows * W * 4)
        view = np.asarray(stage).reshape(rows, W, 4)
        tex = fmt = None
        before = _stamps(src.files)
        with src.bands(rows) as bands:
            if src.half_exact:
                fmt = "RGBA16F"
                tex = _new_layered(src.path, W, H, L, fmt)
                self._upload_bands(tex, src, bands, stage, view)
            else:
                fmt = "RGBA16F" if _bands_half_exact(src, bands, view) else "RGBA32F"
        if tex is None:
            # Two reads of the files: a bake replacing them from the first on must not pass as half-exact.
            tex = _new_layered(src.path, W, H, L, fmt)
            with src.bands(rows) as bands:
                self._upload_bands(tex, src, bands, stage, view)
            if _stamps(src.files) != before:
                raise TextureUploadError(f"{src.path}: changed while it was read (a bake writing it?); "
                                         f"show it again when the bake has finished")
        return tex, L * H * W * 4 * (2 if fmt == "RGBA16F" else 4)

    @staticmethod
    def _upload_bands(tex, src: pp.LayerSource, bands, stage, view: np.ndarray) -> None:
        """Every layer of every band into ``tex`` through the copy pass."""
        sh = gpu_shaders.copy_shader()
        W = src.width
        for band in bands:
            n = band.n
            # A band's texture takes exactly its texels: the last, shorter band gets a buffer of its own.
            data = stage if n == view.shape[0] else gpu.types.Buffer("FLOAT", n * W * 4)
            rows = view[:n] if data is stage else np.asarray(data).reshape(n, W, 4)

            def one_layer(layer, band=band, data=data, rows=rows):
                band.fill_layer(layer, rows)
                one = gpu.types.GPUTexture((W, band.n), format="RGBA32F", data=data)
                sh.uniform_sampler("layerTex", one)
                sh.uniform_int("row0", band.gpu_row)
                return one                      # alive until its layer is drawn

            _draw_layers(tex, W, n, sh, range(src.layers), one_layer, y=band.gpu_row)

    def _texture_2d(self, rgba_bottom_first: np.ndarray):
        H, W, _ = rgba_bottom_first.shape
        return gpu.types.GPUTexture((W, H), format="RGBA32F", data=_buffer(rgba_bottom_first))

    def set_needs(self, s: pp.PreviewSet, want_bounce: bool, want_vertex: bool, bands: int, light,
                  want_sun: bool = False) -> tuple:
        """(GPU bytes, staging bytes) of the set's textures that are not on the
        GPU yet, from the files' headers (pack's ``plan``): what uploading them
        adds to memory (on a software GPU such as llvmpipe the textures are
        this process's memory; on a GPU this errs on the safe side). A file
        whose header cannot be read counts nothing: its upload names it."""
        K = bands * bands
        total = staging = 0

        def add(key, planner):
            nonlocal total, staging
            if key in self._res:
                return
            try:
                nbytes, stage = planner()
            except Exception:       # noqa: BLE001 - an estimate: a damaged file is named by its upload
                return
            total += nbytes
            staging = max(staging, stage)

        add(("transfer", s.key), lambda: pp.transfer_layers(s.transfer).plan())
        if want_bounce and s.has_bounce and s.relight:
            op = lambda: pp.relight_operator_layers(s.relight, expand=False)     # noqa: E731
            add(("relight-op", s.key), lambda: op().plan())
            add(("bounce", s.bounce_key(light)), lambda: (pp.relit_bytes(op()), 0))
        elif want_bounce and s.has_bounce:
            add(("bounce", s.key), lambda: pp.bounce_level_layers(s.bounces, K).plan())
        if want_vertex and s.vertex:
            add(("vertex", s.key), lambda: (2 * _npz_bytes(s.vertex),) * 2)
        if want_sun and s.sun:
            # R16F, or RGBA16F with edges (mask, d, valid, h): read as float32, stacked, then the buffer
            add(("sun", s.key), lambda: (lambda H, W: (8 * H * W, 48 * H * W) if s.sun_edge else (
                2 * H * W, 6 * H * W))(*texture_header(s.sun)[2:4]))
        if want_sun and s.lamps:
            # RGBA16F (a lamp a channel): read as float32, padded to four, then the buffer
            add(("lamps", s.key), lambda: (lambda H, W: (8 * H * W, 48 * H * W))(*texture_header(s.lamps)[2:4]))
        return total, staging

    def planned_bytes(self, ps: pp.PreviewScene, mode: str) -> tuple:
        """(GPU bytes, largest staging) a frame of ``ps`` in ``mode`` still has
        to load: every drawable set's textures (:meth:`set_needs`) and the
        material images, float32 RGBA, not yet uploaded."""
        vertex_mode = mode in VERTEX_MODES
        total = staging = 0
        seen = set()
        for m in ps.meshes:
            s = ps.sets.get(m.set_name)
            if s is None or s.name in seen or (vertex_mode and not s.vertex):
                continue
            seen.add(s.name)
            # the sun (and its bounce) is drawn in the fragment modes
            t, st = self.set_needs(s, ps.use_bounces, vertex_mode, ps.bands, ps.light if vertex_mode else ps.bounce_light,
                                   (ps.sun is not None or bool(ps.lamps)) and not vertex_mode)
            total, staging = total + t, max(staging, st)
        for i, img in enumerate(ps.images):
            key = ps.image_keys[i] if i < len(ps.image_keys) else None
            if ("image", key) not in self._res:
                texels = int(np.prod(np.shape(img)[:2]))
                total, staging = total + 16 * texels, max(staging, 16 * texels)
        return total, staging

    def _set_textures(self, s: pp.PreviewSet, want_bounce: bool, want_vertex: bool, bands: int, light,
                      want_sun: bool = False):
        """The set's (transfer, bounce, vertex, sun) textures, each (GPUTexture, bytes) or
        None; loaded, checked against the bake's band count and uploaded once
        (relightable bounces once per ``light``, (K, 3): :meth:`_relit_bounce`).
        TextureUploadError before anything is read when they would not fit in
        the memory available (:meth:`set_needs`)."""
        key, K = s.key, bands * bands
        need, stage = self.set_needs(s, want_bounce, want_vertex, bands, light, want_sun)
        if need:        # every frame asks; only a set with something to upload reads the memory available
            try:
                check_fits(need + stage, f"{s.transfer}: uploading its set's textures ({need / GiB:.2f} GiB on the "
                           f"GPU)", fraction=MEMORY_FRACTION, advice=MEMORY_ADVICE)
            except MemoryLimitError as exc:
                raise TextureUploadError(str(exc)) from None

        def transfer():
            def upload():
                src = pp.transfer_layers(s.transfer)
                if src.rgb or src.coeffs < K:
                    raise TextureUploadError(f"{s.transfer}: holds {src.coeffs} SH coefficients"
                                             f"{' per colour' if src.rgb else ''}, the bake has {K}; bake again")
                return self._layer_texture(src)
            return _load(upload, s.transfer)

        def bounce():
            if s.relight:
                return self._relit_bounce(s, light, bands)
            where = ", ".join(s.bounces)

            def upload():
                src = pp.bounce_level_layers(s.bounces, K)
                if src.coeffs < K:
                    raise TextureUploadError(f"{where}: holds {src.coeffs} SH coefficients per colour, "
                                             f"the bake has {K}; bake again")
                return self._layer_texture(src)
            return _load(upload, where)

        def vertex():
            data = _load(s.load_vertex, s.vertex)
            _check_coeffs(data, 2, K, s.vertex)
            return self._array_texture(pp.pack_vertex_transfer(data), s.vertex)

        def sun():
            # (H, W) the mask alone, or (H, W, 4) with its edges (mask, d, valid, h); row 0 at the bottom
            tex = np.ascontiguousarray(_load(s.load_sun_texture, s.sun), np.float32)
            H, W = tex.shape[:2]
            _check_limits(s.sun, W, H, 1)
            # Half holds a mask of R <= 2048 rays exactly (multiples of 1 / R), and the edges as written.
            if tex.ndim == 3:
                return gpu.types.GPUTexture((W, H), format="RGBA16F", data=_buffer(tex)), 8 * H * W
            return gpu.types.GPUTexture((W, H), format="R16F", data=_buffer(tex)), 2 * H * W

        def lamps():
            # (H, W, 4) a lamp's mask a channel, row 0 at the bottom; multiples of 1 / LAMP_RAYS: exact in half
            tex = np.ascontiguousarray(_load(s.load_lamp_texture, s.lamps), np.float32)
            H, W = tex.shape[:2]
            _check_limits(s.lamps, W, H, 1)
            return gpu.types.GPUTexture((W, H), format="RGBA16F", data=_buffer(tex)), 8 * H * W

        return (self._get(("transfer", key), transfer),
                self._get(("bounce", s.bounce_key(light)), bounce) if want_bounce and s.has_bounce else None,
                self._get(("vertex", key), vertex) if want_vertex and s.vertex else None,
                self._get(("sun", key), sun) if want_sun and s.sun else None,
                self._get(("lamps", key), lamps) if want_sun and s.lamps else None)

    def _relit_bounce(self, s: pp.PreviewSet, light, bands: int):
        """The bounce texture of relightable set ``s`` under ``light`` (K, 3), made
        on the GPU: the operator is uploaded once, and each light costs one
        relight pass (shaders/prtt_relight_frag.glsl, a quad per output layer),
        no work per texel on the CPU. Returns (GPUTexture, bytes)."""
        K, K4 = bands * bands, pp.layers(bands * bands)
        where = s.relight

        def operator():
            def upload():
                # Shared glossy rows stay shared on the GPU (a third of the layers,
                # half floats): the pass tints them (RELIGHT_SHARED).
                src = pp.relight_operator_layers(where, expand=False)
                if src.coeffs != K:          # the pass reads exactly the bake's K4 layers per colour
                    raise TextureUploadError(f"{where}: holds {src.coeffs} light coefficients, the bake has "
                                             f"{K}; bake again")
                tex, nbytes = self._layer_texture(src)
                return tex, nbytes, src.width, src.height, src.glossy_bands, src.shared
            return _load(upload, where)

        op_tex, _, W, H, gbands, shared = self._get(("relight-op", s.key), operator)
        # float32: relit values are not half-exact as baked ones (read from half EXRs) are,
        # and half rounding moved shaded pixels by 1.3e-3 (tests/test_preview_render.py).
        out = gpu.types.GPUTexture((W, H), layers=3 * K4, format="RGBA32F")
        sh = gpu_shaders.relight_shader(bands, gbands, shared)
        ubo = gpu.types.GPUUniformBuf(_buffer(pp.relight_block(light, bands)))

        def relight_layer(layer):
            sh.uniform_block("relight", ubo)
            sh.uniform_sampler("relightTex", op_tex)
            sh.uniform_int("out_colour", layer // K4)
            sh.uniform_int("out_q", layer % K4)

        _draw_layers(out, W, H, sh, range(3 * K4), relight_layer)
        return out, W * H * 3 * K4 * 16

    def _dummy(self, layered: bool):
        if layered:
            return self._get(("dummy", "array"), lambda: gpu.types.GPUTexture(
                (1, 1), layers=1, format="RGBA32F", data=_buffer(np.zeros(4))))
        return self._get(("dummy", "2d"), lambda: gpu.types.GPUTexture(
            (1, 1), format="RGBA32F", data=_buffer(np.zeros(4))))

    def _mesh_batch(self, m: pp.DrawMesh):
        def make():
            fmt = gpu.types.GPUVertFormat()
            for name, n in (("pos", 3), ("nor", 3), ("uv", 2), ("muv", 2), ("nuv", 2), ("tan", 4), ("vidx", 1)):
                fmt.attr_add(id=name, comp_type="F32", len=n, fetch_mode="FLOAT")
            vbo = gpu.types.GPUVertBuf(fmt, m.positions.shape[0])
            for name, a in (("pos", m.positions), ("nor", m.normals), ("uv", m.uv), ("muv", m.mat_uv),
                            ("nuv", m.nm_uv), ("tan", m.tangents), ("vidx", m.vidx)):
                vbo.attr_fill(name, np.ascontiguousarray(a, np.float32))
            ibo = gpu.types.GPUIndexBuf(type="TRIS", seq=np.ascontiguousarray(m.indices, np.uint32))
            return gpu.types.GPUBatch(type="TRIS", buf=vbo, elem=ibo)
        return self._get(("mesh", m.key or id(m)), make)

    def _light_ubo(self, light: np.ndarray, bands: int):
        L = np.asarray(light, np.float64)[:bands * bands]
        return self._get(("light", bands, _digest(L)), lambda: gpu.types.GPUUniformBuf(_buffer(pp.light_block(L, bands))))

    def _material_ubo(self, mat: pp.PreviewMaterial):
        block = mat.block()
        return self._get(("material", _digest(block)), lambda: gpu.types.GPUUniformBuf(_buffer(block)))

    def _image(self, ps: pp.PreviewScene, i: int):
        key = ps.image_keys[i] if i < len(ps.image_keys) else _digest(ps.images[i])
        return self._get(("image", key), lambda: self._texture_2d(pp.image_rgba(ps.images[i])))

    def _gaunt(self, bands: int):
        return self._get(("gaunt", bands), lambda: self._texture_2d(pp.gaunt_table(bands, GAUNT_WIDTH)))

    def end_frame(self, keep: int = 0) -> None:
        """Free what the last ``keep`` + 1 frames did not use (GPU memory goes
        with Python's last reference)."""
        for k in [k for k, f in self._stamp.items() if f < self._frame - keep]:
            self._res.pop(k, None)
            del self._stamp[k]
        self._frame += 1

    def free(self) -> None:
        self._res.clear()
        self._stamp.clear()
        self._view_ubo = None

    def resource_keys(self) -> list:
        return list(self._res)

    def resource_bytes(self) -> int:
        return sum(v[1] for k, v in self._res.items() if k[0] in ("transfer", "bounce", "vertex", "relight-op"))

    # --- drawing --------------------------------------------------------------------
    def _plan(self, ps: pp.PreviewScene, mode: str, skipped: dict) -> list:
        """[(mesh, textures)] of the meshes ``ps`` can draw in ``mode``, their
        textures loaded and uploaded; the others go to ``skipped`` with why."""
        if mode not in MODES:
            raise ValueError(f"unknown preview mode {mode!r}; use one of {', '.join(MODES)}")
        vertex_mode = mode in VERTEX_MODES
        todo = []
        for m in ps.meshes:
            s = ps.sets.get(m.set_name)
            if s is None:
                skipped[m.name] = "no baked texture set: bake again"
                continue
            if vertex_mode and not s.vertex:
                skipped[m.name] = NO_VERTEX_TRANSFER
                continue
            if vertex_mode and not m.has_vertex_transfer():
                skipped[m.name] = STALE_VERTEX_TRANSFER
                continue
            try:
                tex = self._set_textures(s, ps.use_bounces, vertex_mode, ps.bands,
                                         ps.light if vertex_mode else ps.bounce_light,
                                         (ps.sun is not None or bool(ps.lamps)) and not vertex_mode)
            except TextureUploadError as exc:
                skipped[m.name] = f"cannot use its texture {exc}"
                continue
            todo.append((m, tex))
        return todo

    def prepare(self, ps: pp.PreviewScene, mode: str) -> dict:
        """Load and upload what a frame of ``ps`` in ``mode`` needs, before any
        framebuffer exists; returns {mesh name: why it cannot be drawn} (empty
        when every mesh can). The next :meth:`draw` finds the textures cached."""
        skipped: dict = {}
        self._plan(ps, mode, skipped)
        return skipped

    def draw(self, ps: pp.PreviewScene, mode: str, view_projection, camera, *, exposure: float = 1.0,
             depth_bias: float = 0.0, prepass: bool = True, display=None) -> FrameStats:
        """Draw every mesh of ``ps`` into the bound framebuffer.

        view_projection (4, 4) world -> clip; camera (4,): eye position and 1, or
        unit direction towards the eye and 0 (orthographic). ``display`` (a
        core.shading.display.DisplayTransform): draw the scene's view transform
        for a colour buffer that encodes sRGB (the viewport's); None: linear
        radiance times the exposure (Standard in the viewport; offscreen, the
        caller encodes)."""
        stats = FrameStats()
        todo = self._plan(ps, mode, stats.skipped)
        gamma_inv = 1.0 / display.gamma if display is not None else 0.0
        view_data = _buffer(pp.view_block(view_projection, camera, exposure, ps.bands, depth_bias, gamma_inv))
        if self._view_ubo is None:
            self._view_ubo = gpu.types.GPUUniformBuf(view_data)
        else:
            self._view_ubo.update(view_data)
        if not todo:
            return stats
        light = self._light_ubo(ps.light, ps.bands)
        old_test, old_mask = gpu.state.depth_test_get(), gpu.state.depth_mask_get()
        try:
            gpu.state.depth_test_set("LESS_EQUAL")
            if prepass and mode in FRAGMENT_MODES:
                depth = gpu_shaders.depth_shader()
                depth.bind()
                depth.uniform_block("view", self._view_ubo)
                gpu.state.depth_mask_set(True)
                gpu.state.color_mask_set(False, False, False, False)
                for m, _ in todo:
                    depth.uniform_float("ModelMatrix", _matrix(m.matrix))
                    self._mesh_batch(m).draw(depth)
                gpu.state.color_mask_set(True, True, True, True)
                gpu.state.depth_mask_set(False)
            else:
                gpu.state.depth_mask_set(True)
            lut = self._display_lut(display) if display is not None else None
            sun_ubo = (self._get(("sun-block", ps.sun), lambda: gpu.types.GPUUniformBuf(_buffer(ps.sun.block())))
                       if ps.sun is not None else None)
            block = pp.lamp_block(ps.lamps)
            lamp_ubo = (self._get(("lamp-block", block.tobytes()), lambda: gpu.types.GPUUniformBuf(_buffer(block)))
                        if ps.lamps else None)
            for m, (transfer, bounce, vertex, sun, lamps) in todo:
                self._draw_mesh(ps, m, mode, light, transfer, bounce, vertex, lut,
                                (sun[0], sun_ubo) if sun is not None and ps.sun is not None else None,
                                (lamps[0], lamp_ubo) if lamps is not None and lamp_ubo is not None else None)
                stats.drawn.append(m.name)
                stats.triangles += m.triangles
        finally:
            gpu.state.depth_mask_set(old_mask)
            gpu.state.depth_test_set(old_test)
            gpu.state.color_mask_set(True, True, True, True)
        stats.texture_bytes = self.resource_bytes()
        return stats

    def _display_lut(self, display):
        """The display table as a 3D texture (RGBA16F: 2**-11 relative steps,
        below an 8-bit display's; the GPU filters it trilinearly)."""
        n = display.size
        return self._get(("display", display.lut_digest), lambda: gpu.types.GPUTexture(
            (n, n, n), format="RGBA16F", data=_buffer(display.block())))

    def _draw_mesh(self, ps, m, mode, light, transfer, bounce, vertex, lut=None, sun=None, lamps=None):
        sh = gpu_shaders.surface_shader(mode, ps.bands, bounce is not None, lut is not None, sun is not None,
                                        lamps is not None)
        sh.bind()
        if sun is not None:
            sh.uniform_sampler("sunTex", sun[0])
            sh.uniform_block("sun", sun[1])
        if lamps is not None:
            sh.uniform_sampler("lampTex", lamps[0])
            sh.uniform_block("lamps", lamps[1])
        if lut is not None:
            sh.uniform_sampler("displayLut", lut)
        sh.uniform_block("view", self._view_ubo)
        sh.uniform_block("light", light)
        sh.uniform_float("ModelMatrix", _matrix(m.matrix))
        # Every mode reads the normal: the layering's n.v (prtt_layering.glsl), the sun's n.l.
        sh.uniform_float("NormalMatrix", _matrix(pp.normal_matrix(m.matrix)))
        if mode in FRAGMENT_MODES:
            sh.uniform_sampler("transferTex", transfer[0])
        if vertex is not None:
            sh.uniform_sampler("vertexTex", vertex[0])
        if bounce is not None:
            sh.uniform_sampler("bounceTex", bounce[0])
        if mode in ("tp", "vertex-tp"):
            sh.uniform_sampler("gauntTex", self._gaunt(ps.bands))
        batch = self._mesh_batch(m)
        dummy = self._dummy(False)
        for mat_index, first, count in m.ranges:
            mat = ps.materials[mat_index] if 0 <= mat_index < len(ps.materials) else pp.PreviewMaterial()
            if not ps.normal_maps and mat.normal_texture >= 0:
                mat = dataclasses.replace(mat, normal_texture=-1)
            sh.uniform_block("material", self._material_ubo(mat))
            sh.uniform_sampler("baseTex", self._image(ps, mat.base_texture) if mat.base_texture >= 0 else dummy)
            sh.uniform_sampler("roughTex", self._image(ps, mat.roughness_texture)
                               if mat.roughness_texture >= 0 else dummy)
            if mode in FRAGMENT_MODES:
                sh.uniform_sampler("normalTex", self._image(ps, mat.normal_texture)
                                   if mat.normal_texture >= 0 else dummy)
            batch.draw_range(sh, elem_start=3 * first, elem_count=3 * count)


def _draw_layers(target, width: int, height: int, shader, layers, setup, y: int = 0) -> None:
    """Draw a quad over rows ``y`` .. ``y + height - 1`` (all ``width``
    columns) of each of ``layers`` of 2D array texture ``target`` with
    ``shader``: ``setup(layer)`` sets its inputs after it is bound (what it
    returns is kept until the layer is drawn). No depth test, no blending;
    the viewport and those states are restored."""
    quad = batch_for_shader(shader, "TRI_STRIP", {"pos": ((-1.0, -1.0), (1.0, -1.0), (-1.0, 1.0), (1.0, 1.0))})
    viewport = gpu.state.viewport_get()
    old_test, old_blend = gpu.state.depth_test_get(), gpu.state.blend_get()
    gpu.state.depth_test_set("NONE")
    gpu.state.blend_set("NONE")
    try:
        for layer in layers:
            fb = gpu.types.GPUFrameBuffer(color_slots=(layer_slot(target, layer),))
            with fb.bind():
                gpu.state.viewport_set(0, y, width, height)
                shader.bind()
                keep = setup(layer)
                quad.draw(shader)
            del fb, keep
    finally:
        gpu.state.viewport_set(*viewport)
        gpu.state.depth_test_set(old_test)
        gpu.state.blend_set(old_blend)


def _stamps(paths) -> list:
    """(inode, mtime, size) of each file: what tells a rewritten file."""
    out = []
    for p in paths:
        st = os.stat(p)
        out.append((st.st_ino, st.st_mtime_ns, st.st_size))
    return out


def _npz_bytes(path: str) -> int:
    """Uncompressed bytes of a .npz's arrays (what loading it takes), from its zip directory."""
    with zipfile.ZipFile(path) as z:
        return sum(i.file_size for i in z.infolist())


def _check_limits(path: str, W: int, H: int, L: int) -> None:
    """TextureUploadError naming ``path`` for a W x H x L array texture beyond
    the GL limits: drivers answer one with an anonymous allocation failure."""
    size, layers = gpu.capabilities.max_texture_size_get(), gpu.capabilities.max_texture_layers_get()
    if W > size or H > size or L > layers:
        raise TextureUploadError(f"{path}: {W}x{H} texels in {L} layers exceeds this GPU's limits "
                                 f"({size} texels per side, {layers} layers); bake at a lower resolution")


def _new_layered(path: str, W: int, H: int, L: int, fmt: str, data=None):
    """A W x H x L 2D array texture (empty, or from ``data``: a gpu Buffer);
    TextureUploadError naming ``path`` when the GPU cannot allocate it."""
    try:
        if data is None:
            return gpu.types.GPUTexture((W, H), layers=L, format=fmt)
        return gpu.types.GPUTexture((W, H), layers=L, format=fmt, data=data)
    except RuntimeError as exc:     # out of (GPU) memory
        raise TextureUploadError(f"{path}: the GPU could not allocate its {W}x{H}x{L} {fmt} "
                                 f"texture ({exc}); bake at a lower resolution") from exc


def _bands_half_exact(src: pp.LayerSource, bands, view: np.ndarray) -> bool:
    """Whether every layer of every band is a half float (stops at the first that is not)."""
    for band in bands:
        for layer in range(src.layers):
            band.fill_layer(layer, view[:band.n])
            if not pp.half_exact(view[:band.n]):
                return False
    return True


def _load(loader, path: str) -> np.ndarray:
    """``loader()``, its failures (missing, truncated or foreign files) as a
    TextureUploadError naming the file."""
    try:
        data = loader()
    except TextureUploadError:              # already names the file and what to do
        raise
    except TextureError as exc:             # core.io.exr_io's messages start with the file
        raise TextureUploadError(f"{exc}; bake again") from exc
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile) as exc:   # a damaged .npz
        raise TextureUploadError(f"{path}: unreadable ({exc}); bake again") from exc
    if data is None:
        raise TextureUploadError(f"{path}: holds no data; bake again")
    return data


def _check_coeffs(data: np.ndarray, ndim: int, K: int, path: str) -> None:
    """A texture must hold at least the bake's K coefficients in its last axis
    (fewer would leave layers the shaders read empty: a silently dark image)."""
    if data.ndim != ndim or data.shape[-1] < K:
        raise TextureUploadError(f"{path}: holds {data.shape[-1] if data.ndim else 0} SH coefficients "
                                 f"in shape {data.shape}, the bake has {K}; bake again")


class OffscreenError(RuntimeError):
    """The GPU cannot make the offscreen image asked for (too large)."""


def new_offscreen(width: int, height: int):
    """A float32 RGBA offscreen buffer, or OffscreenError saying what was refused.

    Checked against the GL texture size limit first; drivers also refuse sizes
    within it (Mesa's llvmpipe: no single texture much over 1.5 GiB), which
    only the allocation can tell."""
    limit = gpu.capabilities.max_texture_size_get()
    if width > limit or height > limit:
        raise OffscreenError(f"{width}x{height} exceeds this GPU's largest image, {limit} pixels per side")
    try:
        return gpu.types.GPUOffScreen(width, height, format="RGBA32F")
    except RuntimeError as exc:
        gib = width * height * 16 / 1024 ** 3
        raise OffscreenError(f"the GPU could not allocate a {width}x{height} float image "
                             f"({gib:.1f} GiB): {exc}") from exc


def read_pixels(fb, width: int, height: int) -> np.ndarray:
    """(H, W, 4) float32 of the bound framebuffer, row 0 at the bottom."""
    buf = gpu.types.Buffer("FLOAT", width * height * 4)
    fb.read_color(0, 0, width, height, 4, 0, "FLOAT", data=buf)
    return np.asarray(buf).reshape(height, width, 4).copy()


def render_offscreen(renderer: Renderer, ps: pp.PreviewScene, mode: str, view_projection, camera,
                     width: int, height: int, *, exposure: float = 1.0, prepass: bool = True,
                     background=(0.0, 0.0, 0.0, 0.0), display=None) -> tuple[np.ndarray, FrameStats]:
    """Render to a float32 offscreen buffer: (H, W, 4) linear RGBA, row 0 at the bottom.

    Raises OffscreenError when the GPU cannot make a buffer that large."""
    off = new_offscreen(width, height)
    try:
        with off.bind():
            fb = gpu.state.active_framebuffer_get()
            fb.clear(color=tuple(background), depth=1.0)
            gpu.state.viewport_set(0, 0, width, height)
            stats = renderer.draw(ps, mode, view_projection, camera, exposure=exposure, prepass=prepass,
                                  display=display)
            pixels = read_pixels(fb, width, height)
        renderer.end_frame()
    finally:
        off.free()
    return pixels, stats
