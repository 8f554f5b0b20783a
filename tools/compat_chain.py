"""The chain a new user runs, inside one Blender (a bpy module's Python),
through the installed extension zip only. Run by tools/compat.py:

    <bpy venv>/bin/python tools/compat_chain.py ZIP WORK

(with BLENDER_USER_RESOURCES pointing at an empty folder and no PYTHONPATH,
so that nothing of the source tree can be imported). In a fresh factory
scene: install and enable the zip with ``package_install_files``, a plane and
a monkey with a Principled material (a float image as its base colour, so
the glTF export re-encodes it), the Forest studio light as the World, a
camera; then

* Unwrap (Smart UV Project, the default) and Bake Transfer with the add-on's
  defaults (1024², 256 rays, one relightable bounce);
* the viewport draw handler's draw (``draw.draw_view`` into an offscreen
  buffer) and Render Preview Image in the texture modes (TPFL, TP, Diffuse);
* bake again as a user changing settings does: Unwrap with xatlas (the pinned
  wheel, so the UVs are the same in every Blender), a Sun lamp added, 128²,
  64 rays, Vertex Transfer on; Render Preview Image in the vertex modes, and
  in TPFL with the sun and with it hidden (the sun's share of the picture),
  and with a point lamp and a spot (their masks baked) and with them hidden;
  Export glTF.

Prints one JSON object on the last line of stdout (``COMPAT {...}``): each
step's outcome ("ok" or the error's last line), seconds, the preview's
mean pixel per mode, both bakes' files with their SHA-256 and the SHA-256
of the UV maps they baked with. Never raises: a failed step is recorded,
and the steps after it are skipped.
"""
import hashlib
import json
import os
import sys
import time
import traceback

import bpy

STEPS = ("install", "unwrap", "bake", "draw_handler", "render", "bake_again", "render_vertex", "render_sun",
         "render_lamps",
         "export")


def _uv_sha256():
    """SHA-256 of every mesh's PRTT UV map (float32, object name order)."""
    import numpy as np
    h = hashlib.sha256()
    for ob in sorted((o for o in bpy.context.scene.objects if o.type == "MESH"), key=lambda o: o.name):
        uv = ob.data.uv_layers.get("PRTT")
        if uv is not None:
            a = np.empty(2 * len(uv.data), np.float32)
            uv.data.foreach_get("uv", a)
            h.update(ob.name.encode() + a.tobytes())
    return h.hexdigest()


def _hash_outputs(out_dir):
    """{file: SHA-256} of the bake's textures (the manifest carries times and paths: listed, not hashed)."""
    return {name: (_sha256(os.path.join(out_dir, name)) if name.endswith(".exr") else None)
            for name in sorted(os.listdir(out_dir)) if name.endswith(".exr") or name == "manifest.json"}


def _sha256(path):
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _world():
    """The Forest studio HDRI that Blender ships, as an Environment Texture World."""
    path = os.path.join(bpy.utils.system_resource("DATAFILES"), "studiolights", "world", "forest.exr")
    world = bpy.data.worlds.new("Forest")
    if hasattr(world, "use_nodes") and bpy.app.version < (5, 0, 0):
        world.use_nodes = True
    nt = world.node_tree
    env = nt.nodes.new("ShaderNodeTexEnvironment")
    env.image = bpy.data.images.load(path)
    nt.links.new(env.outputs["Color"], nt.nodes["Background"].inputs["Color"])
    return world


def _material():
    """A Principled material whose base colour is a float image (linear, so the
    export writes the preview's pixels rather than the file's)."""
    mat = bpy.data.materials.new("Checker")
    if hasattr(mat, "use_nodes") and bpy.app.version < (5, 0, 0):
        mat.use_nodes = True
    img = bpy.data.images.new("checker", 8, 8, float_buffer=True)
    px = [0.0] * (8 * 8 * 4)
    for y in range(8):
        for x in range(8):
            v = 0.7 if (x + y) % 2 else 0.2
            px[4 * (8 * y + x):4 * (8 * y + x) + 4] = [v, 0.5 * v, 0.3, 1.0]
    img.pixels = px
    nt = mat.node_tree
    tex = nt.nodes.new("ShaderNodeTexImage")
    tex.image = img
    bsdf = next(n for n in nt.nodes if n.bl_idname == "ShaderNodeBsdfPrincipled")
    nt.links.new(tex.outputs["Color"], bsdf.inputs["Base Color"])
    bsdf.inputs["Roughness"].default_value = 0.3
    return mat


def _scene(out_dir, size):
    sc = bpy.context.scene
    sc.world = _world()
    bpy.ops.mesh.primitive_plane_add(size=4)
    bpy.context.active_object.data.materials.append(_material())
    bpy.ops.mesh.primitive_monkey_add(location=(0, 0, 1))
    bpy.ops.object.shade_smooth()
    monkey = bpy.context.active_object
    bpy.ops.object.camera_add(location=(4, -4, 3), rotation=(1.0, 0.0, 0.8))
    sc.camera = bpy.context.active_object
    for o in sc.objects:                          # the meshes selected, as a user does before Unwrap
        o.select_set(o.type == "MESH")
    bpy.context.view_layer.objects.active = monkey
    sc.render.resolution_x, sc.render.resolution_y = size
    sc.render.resolution_percentage = 100
    sc.prtt.output_dir = out_dir


def main(zip_path, work):
    result = {"blender": bpy.app.version_string, "python": sys.version.split()[0],
              "steps": {}, "seconds": {}, "preview": {}, "files": {}, "notes": []}
    try:
        import numpy
        result["numpy"] = numpy.__version__
    except ImportError:
        pass
    out_dir = os.path.join(work, "textures")

    def step(name, fn):
        if any(v != "ok" for v in result["steps"].values()):
            result["steps"][name] = "skipped"
            return None
        t0 = time.perf_counter()
        try:
            got = fn()
            result["steps"][name] = "ok"
            return got
        except BaseException as exc:          # noqa: BLE001 - every failure is this step's result
            traceback.print_exc()
            lines = [ln for ln in f"{type(exc).__name__}: {exc}".splitlines() if ln.strip()]
            result["steps"][name] = lines[-1][:300] if lines else type(exc).__name__
        finally:
            result["seconds"][name] = round(time.perf_counter() - t0, 2)

    def install():
        import importlib.util
        if importlib.util.find_spec("prtt_addon") is not None:
            raise RuntimeError("a prtt_addon outside the installed extension is importable")
        bpy.ops.wm.read_factory_settings(use_empty=True)
        bpy.ops.extensions.package_install_files(filepath=zip_path, repo="user_default", enable_on_install=True)
        if "bl_ext.user_default.prtt_addon" not in bpy.context.preferences.addons:
            raise RuntimeError("installed but not enabled")
        import bl_ext.user_default.prtt_addon as pkg
        result["installed_at"] = os.path.dirname(pkg.__file__)
        try:
            import numba  # noqa: F401
            result["numba"] = numba.__version__
        except ImportError:
            result["numba"] = None
        _scene(out_dir, (64, 48))

    def ok(ret, what):
        if ret != {"FINISHED"}:
            raise RuntimeError(f"{what} returned {ret}")

    step("install", install)
    step("unwrap", lambda: ok(bpy.ops.prtt.unwrap(), "unwrap"))

    def bake():
        ok(bpy.ops.prtt.bake_transfer(), "bake_transfer")
        st = bpy.context.scene.prtt
        result["bake_settings"] = {k: getattr(st, k) for k in ("resolution", "rays", "bounces", "bounce_mode")
                                   if hasattr(st, k)}
        result["default_bake"] = {"uv": _uv_sha256(), "files": _hash_outputs(out_dir)}
        with open(os.path.join(out_dir, "manifest.json"), encoding="utf-8") as f:
            sets = (json.load(f).get("bounce") or {}).get("sets", [])
        # "compiled" when the worker shaded the bounce's hits with numba's loops.
        result["hit_shading"] = sorted({s.get("hit_shading", "?") for s in sets})

    step("bake", bake)

    def draw_handler():
        # What the POST_VIEW handler runs, into an offscreen buffer as a
        # viewport's framebuffer (background mode has no viewports).
        import gpu
        import numpy as np
        from bl_ext.user_default.prtt_addon.blender.preview import draw as preview_draw
        from bl_ext.user_default.prtt_addon.blender.preview.offscreen import ensure_gpu
        ensure_gpu()
        sc = bpy.context.scene
        cam = sc.camera
        w, h = sc.render.resolution_x, sc.render.resolution_y
        proj = cam.calc_matrix_camera(bpy.context.evaluated_depsgraph_get(), x=w, y=h)
        view = cam.matrix_world.inverted()

        class RegionData:                      # what a 3D viewport's region data provides
            perspective_matrix = proj @ view
            view_matrix = view
            is_perspective = True

        sc.prtt.preview = True

        def draw():
            off = gpu.types.GPUOffScreen(w, h, format="RGBA32F")
            try:
                with off.bind():
                    fb = gpu.state.active_framebuffer_get()
                    fb.clear(color=(0, 0, 0, 0), depth=1.0)
                    stats = preview_draw.draw_view(bpy.context, RegionData())
                    buf = fb.read_color(0, 0, w, h, 4, 0, "FLOAT")
                buf.dimensions = w * h * 4
                px = np.array(buf, dtype=np.float32).reshape(h, w, 4)
            finally:
                off.free()
            if stats is None or not stats.drawn:
                raise RuntimeError(f"the draw handler drew nothing: {preview_draw.last_status}")
            return px

        # Standard first: linear radiance, comparable across versions (4.2's HDRI differs)
        view = sc.view_settings.view_transform
        sc.view_settings.view_transform = "Standard"
        result["preview"]["draw_handler"] = round(float(draw()[..., :3].mean()), 6)
        # then the scene's own view transform (Blender's default, AgX), sampled from this Blender
        from bl_ext.user_default.prtt_addon.blender.preview.colour_management import display_of
        sc.view_settings.view_transform = view
        table = display_of(sc)
        grey = table.encode(np.array([[0.01] * 3, [0.18] * 3, [1.0] * 3, [8.0] * 3]))[:, 0] if table else []
        result["display"] = {"name": table.name if table else "Standard", "grey": [round(float(g), 5) for g in grey],
                             "draw_handler": round(float(draw()[..., :3].mean()), 6)}
        # what the preview read from Blender: the light, the materials, the images
        from bl_ext.user_default.prtt_addon.blender.preview import drawlist
        ps, _ = drawlist.collect(bpy.context)
        result["preview_scene"] = {
            "light_dc": [round(float(v), 6) for v in ps.light[0]],
            "materials": [repr(m) for m in ps.materials],
            "image_means": [round(float(np.asarray(i, np.float64).mean()), 6) for i in ps.images]}

    step("draw_handler", draw_handler)

    def picture(mode):
        import numpy as np
        bpy.context.scene.prtt.preview_mode = mode
        ok(bpy.ops.prtt.render_preview(), f"render_preview in mode {mode}")
        img = bpy.data.images["PRTT Preview"]
        px = np.empty(len(img.pixels), np.float32)
        img.pixels.foreach_get(px)
        px = px.reshape(-1, 4)
        if not np.isfinite(px).all():
            raise RuntimeError(f"mode {mode}: non-finite pixels")
        if px[:, 3].max() < 1.0:
            raise RuntimeError(f"mode {mode}: nothing drawn")
        return float(px[:, :3].mean())

    def render(modes=("TPFL", "TP", "DIFFUSE")):
        for mode in modes:
            result["preview"][mode] = round(picture(mode), 6)

    step("render", render)

    def bake_again():
        st = bpy.context.scene.prtt
        st.unwrap_method, st.resolution, st.rays, st.vertex_transfer = "XATLAS", 128, 64, True
        ok(bpy.ops.prtt.unwrap(), "unwrap (xatlas)")
        bpy.ops.object.light_add(type="SUN", rotation=(0.7, 0.2, 0.5))      # its shadows baked as a mask
        bpy.context.active_object.data.energy = 2.0
        # a point lamp and a spot: their masks baked, their light drawn (issue 49)
        bpy.ops.object.light_add(type="POINT", location=(1.5, -1.0, 2.0))
        bpy.context.active_object.data.energy = 200.0
        bpy.ops.object.light_add(type="SPOT", location=(-1.5, -1.5, 2.5), rotation=(0.6, 0.0, -0.8))
        bpy.context.active_object.data.energy = 300.0
        ok(bpy.ops.prtt.bake_transfer(), "bake_transfer (again)")
        result["uv"] = _uv_sha256()
        result["files"] = _hash_outputs(out_dir)

    step("bake_again", bake_again)
    step("render_vertex", lambda: render(("VERTEX_TPFL", "VERTEX_TP")))

    def render_sun():
        from bl_ext.user_default.prtt_addon.blender.preview import drawlist
        sun = next(o for o in bpy.context.scene.objects if o.type == "LIGHT" and o.data.type == "SUN")
        ps, status = drawlist.collect(bpy.context)
        lit = picture("TPFL")
        sun.hide_render = True
        try:
            unlit = picture("TPFL")
        finally:
            sun.hide_render = False
        result["sun"] = {"drawn": ps.sun is not None, "panel": status.sun_description,
                         "share": round(lit - unlit, 6)}

    step("render_sun", render_sun)

    def render_lamps():
        from bl_ext.user_default.prtt_addon.blender.preview import drawlist
        lamps = [o for o in bpy.context.scene.objects if o.type == "LIGHT" and o.data.type in ("POINT", "SPOT")]
        ps, status = drawlist.collect(bpy.context)
        lit = picture("TPFL")
        for o in lamps:
            o.hide_render = True
        try:
            unlit = picture("TPFL")
        finally:
            for o in lamps:
                o.hide_render = False
        result["lamps"] = {"drawn": [lp.name for lp in ps.lamps], "panel": status.lamps_description,
                           "share": round(lit - unlit, 6)}

    step("render_lamps", render_lamps)

    def export():
        glb = os.path.join(work, "scene.glb")
        ok(bpy.ops.prtt.export_gltf(filepath=glb), "export_gltf")
        result["glb"] = glb
        result["glb_bytes"] = os.path.getsize(glb)

    step("export", export)
    print("\nCOMPAT " + json.dumps(result), flush=True)   # on a line of its own


if __name__ == "__main__":
    main(os.path.abspath(sys.argv[1]), os.path.abspath(sys.argv[2]))
