"""PRTT's operators: Unwrap, Bake Transfer (modal in the UI, blocking headless), Cancel."""
import bpy
from bpy_extras.io_utils import ExportHelper

from ...core.texels.unwrap import UnwrapError
from ..bake import run as bake_run
from ..gltf.export import GltfExportError, export_glb
from ..preview.offscreen import RenderError, exposure_of, render_scene
from ..rna_arrays import RnaArrayError, write_pixels
from ..scene.job import ExportError, unwrap_resolution
from ..scene.uv_maps import bake_downscale, unwrap_objects
from ..shared import PREVIEW_MODES
from .panels import draw_progress

#: Scenes whose running bake the Cancel button asked to stop (read by the modal operator).
_CANCEL_REQUESTS: set = set()


class PRTT_OT_unwrap(bpy.types.Operator):
    """Lay out the selected meshes in the dedicated "PRTT" UV map (other UV maps stay as they are)"""

    bl_idname = "prtt.unwrap"
    bl_label = "Unwrap"
    bl_options = {"REGISTER", "UNDO"}

    @classmethod
    def poll(cls, context):
        if context.mode not in {"OBJECT", "EDIT_MESH"}:
            cls.poll_message_set("Unwrap works from Object or Edit Mode")
            return False
        meshes = [o for o in context.selected_objects if o.type == "MESH"]
        if not meshes:
            cls.poll_message_set("Select one or more mesh objects (others get UVs when baked)")
            return False
        if all(o.library is not None or o.data.library is not None for o in meshes):
            cls.poll_message_set("Linked meshes cannot be changed; they get UVs when baked")
            return False
        return True

    def execute(self, context):
        st = context.scene.prtt
        objects = [o for o in context.selected_objects if o.type == "MESH"]
        faceless = [o.name for o in objects if len(o.data.polygons) == 0]
        try:
            overlaps = unwrap_objects(context, objects, method=st.unwrap_method, resolution=st.resolution,
                                      padding=st.padding, atlas=st.texture_sets == "ATLAS",
                                      source_map=st.existing_uv_map, dilate=st.dilate,
                                      bounce_downscale=bake_downscale(st),
                                      resolution_of=lambda ob: unwrap_resolution(ob, st))
        except (UnwrapError, RnaArrayError, RuntimeError) as exc:
            self.report({"ERROR"}, f"PRTT: {exc}")
            return {"CANCELLED"}
        bad = {k: v for k, v in overlaps.items() if v}
        if bad:
            self.report({"WARNING"}, "PRTT: overlapping UV islands in " + ", ".join(
                f"{k} ({v} texels)" for k, v in bad.items()) + "; they would bake wrongly there")
        else:
            self.report({"INFO"}, f"PRTT: unwrapped {len(overlaps)} object(s) into the 'PRTT' UV map")
        if faceless:
            self.report({"WARNING"}, f"PRTT: skipped {len(faceless)} object(s) without faces: "
                        f"{', '.join(faceless[:8])}")
        return {"FINISHED"}


class PRTT_OT_bake_transfer(bpy.types.Operator):
    """Bake transfer (and bounce) textures in a separate process; Esc cancels"""

    bl_idname = "prtt.bake_transfer"
    bl_label = "Bake Transfer"
    # One undo step once the bake has changed the scene (its record and the
    # AO images): pushed when the operator finishes, not when it is cancelled.
    bl_options = {"UNDO"}

    force: bpy.props.BoolProperty(name="Force", default=False,
                                  description="Bake even if the inputs did not change", options={"SKIP_SAVE"})

    _timer = None
    _watch = None           # bake_run.BakeWatch of the running bake

    @classmethod
    def poll(cls, context):
        if context.scene.prtt.baking:
            cls.poll_message_set("A bake is running (Esc or Cancel stops it)")
            return False
        if context.mode != "OBJECT":
            cls.poll_message_set("Bake from Object Mode (edit-mode changes are not in the scene yet)")
            return False
        return True

    def execute(self, context):
        # Background mode, scripts and the command lines: run to the end.
        def progress(e):
            if e.get("type") == "progress":
                print(f"PRTT: {e.get('stage')} {e.get('set', '')} {100 * e.get('fraction', 0):.0f}%", flush=True)
            elif e.get("type") == "warning":
                print(f"PRTT warning: {e['message']}", flush=True)
            elif e.get("type") == "info":
                print(f"PRTT: {e['message']}", flush=True)

        outcome = bake_run.bake_blocking(context, force=self.force, on_event=progress)
        return self._report(outcome)

    def invoke(self, context, event):
        if bpy.app.background:
            return self.execute(context)
        st = context.scene.prtt
        try:
            prepared = bake_run.prepare(context)
        except (ExportError, ValueError, OSError) as exc:
            st.status = str(exc)
            self.report({"ERROR"}, f"PRTT: {exc}")
            return {"CANCELLED"}
        for w in prepared.export.warnings:
            self.report({"WARNING"}, f"PRTT: {w}")
        self._watch = bake_run.BakeWatch.start(context, prepared, force=self.force, on_event=self._on_event)
        wm = context.window_manager
        self._timer = wm.event_timer_add(0.1, window=context.window)
        wm.modal_handler_add(self)
        if context.workspace is not None:
            # The status bar shows a bar too (not wm.progress_begin: that turns the cursor into a counter).
            context.workspace.status_text_set(_status_bar)
        return {"RUNNING_MODAL"}

    def _on_event(self, e):
        if e.get("type") == "warning":
            self.report({"WARNING"}, f"PRTT: {e['message']}")
        elif e.get("type") == "info":
            self.report({"INFO"}, f"PRTT: {e['message']}")

    def modal(self, context, event):
        if event.type == "ESC" or (context.scene.name in _CANCEL_REQUESTS and not self._watch.cancelled):
            _CANCEL_REQUESTS.discard(context.scene.name)
            self._watch.cancel(context)
            return {"RUNNING_MODAL"}
        if event.type != "TIMER":
            return {"PASS_THROUGH"}
        outcome = self._watch.poll(context)
        if outcome is None:
            for area in context.screen.areas if context.screen else []:
                if area.type in {"VIEW_3D", "STATUSBAR"}:
                    area.tag_redraw()
            return {"RUNNING_MODAL"}
        self._cleanup(context)
        return self._report(outcome)

    def _cleanup(self, context):
        wm = context.window_manager
        if self._timer is not None:
            wm.event_timer_remove(self._timer)
        if context.workspace is not None:
            context.workspace.status_text_set(None)

    def _report(self, outcome):
        level = {"done": "INFO", "skipped": "INFO", "cancelled": "WARNING"}.get(outcome.status, "ERROR")
        self.report({level}, outcome.message)
        return {"FINISHED"} if outcome.status in ("done", "skipped") else {"CANCELLED"}


def _status_bar(header, context):
    """Status bar while baking: a progress bar, what runs, how to stop it."""
    st = context.scene.prtt
    row = header.layout.row(align=True)
    row.label(text="PRTT")
    draw_progress(row, st)
    row.label(text="Esc cancels")


class PRTT_OT_cancel_bake(bpy.types.Operator):
    """Cancel the running bake (the previous textures stay as they were)"""

    bl_idname = "prtt.cancel_bake"
    bl_label = "Cancel Bake"

    @classmethod
    def poll(cls, context):
        if not context.scene.prtt.baking:
            cls.poll_message_set("No bake is running")
            return False
        return True

    def execute(self, context):
        _CANCEL_REQUESTS.add(context.scene.name)
        context.scene.prtt.status = "cancelling"
        return {"FINISHED"}


class PRTT_OT_render_preview(bpy.types.Operator):
    """Render the PRTT preview from the scene camera at the render size into the image PRTT Preview"""

    bl_idname = "prtt.render_preview"
    bl_label = "Render Preview Image"

    @classmethod
    def poll(cls, context):
        if not context.scene.prtt.last_bake:
            cls.poll_message_set("Nothing baked yet: Bake Transfer first")
            return False
        if context.scene.camera is None:
            cls.poll_message_set("The scene has no camera to render from")
            return False
        return True

    def execute(self, context):
        st = context.scene.prtt
        mode = PREVIEW_MODES[st.preview_mode]
        try:
            pixels, stats, status, seconds = render_scene(context, mode=mode, bounces=st.preview_bounces)
        except (RenderError, ValueError, OSError) as exc:
            self.report({"ERROR"}, f"PRTT: {exc}")
            return {"CANCELLED"}
        h, w = pixels.shape[:2]
        img = bpy.data.images.get("PRTT Preview")
        if img is not None and tuple(img.size) != (w, h):
            bpy.data.images.remove(img)
            img = None
        if img is None:
            img = bpy.data.images.new("PRTT Preview", w, h, float_buffer=True, alpha=True)
        px = pixels.copy()
        px[..., :3] *= exposure_of(context.scene)
        write_pixels(img, px)                     # bottom row first, like ours
        bake_run.keep_image(img)
        for level, text in status.messages:
            if level != "INFO":
                self.report({"WARNING"}, f"PRTT: {text}")
        self.report({"INFO"}, f"PRTT: {mode} preview {w}x{h} in {1000 * seconds:.0f} ms "
                              f"({len(stats.drawn)} object(s)) -> image 'PRTT Preview'")
        return {"FINISHED"}


class PRTT_OT_export_gltf(bpy.types.Operator, ExportHelper):
    """Export the baked scene as a .glb: Blender's glTF with PRTT's transfer textures (the .blend is not changed)"""

    bl_idname = "prtt.export_gltf"
    bl_label = "Export glTF (PRTT)"
    filename_ext = ".glb"
    filter_glob: bpy.props.StringProperty(default="*.glb", options={"HIDDEN"})

    @classmethod
    def poll(cls, context):
        if not context.scene.prtt.last_bake:
            cls.poll_message_set("Nothing baked yet: Bake Transfer first")
            return False
        if context.scene.prtt.baking:
            cls.poll_message_set("A bake is running")
            return False
        return True

    def execute(self, context):
        try:
            summary = export_glb(context, self.filepath)
        except (GltfExportError, ValueError, OSError) as exc:
            self.report({"ERROR"}, f"PRTT: {exc}")
            return {"CANCELLED"}
        for note in summary["notes"]:
            self.report({"WARNING"}, f"PRTT: {note}")
        self.report({"INFO"}, f"PRTT: exported {summary['objects']} object(s), {summary['bytes']:,} bytes "
                              f"to {self.filepath}")
        return {"FINISHED"}


_CLASSES = (PRTT_OT_unwrap, PRTT_OT_bake_transfer, PRTT_OT_cancel_bake, PRTT_OT_render_preview,
            PRTT_OT_export_gltf)


def register():
    for c in _CLASSES:
        bpy.utils.register_class(c)


def unregister():
    for c in reversed(_CLASSES):
        bpy.utils.unregister_class(c)
