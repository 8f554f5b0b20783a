"""Running ``python -m prtt_addon.worker`` as a child of Blender's Python.

The child is started with Blender's own interpreter and search path
(core/base/child.py). Reader threads move its JSON lines into a queue, so the UI
polls without blocking; ``cancel`` sends SIGTERM (the worker stops and leaves
the previous textures untouched).
"""
from __future__ import annotations

import os
import queue
import signal
import subprocess
import threading

from ...core.base.child import child_env, python_executable
from ...core.base.worker_events import read_event


class WorkerJob:
    def __init__(self, job_path: str, out_dir: str, *, force: bool = False, dask: str | None = None):
        self.cmd = [python_executable(), "-m", "prtt_addon.worker", job_path, out_dir]
        if force:
            self.cmd.append("--force")
        if dask:
            self.cmd += ["--dask", dask]
        self.proc = None
        self._events: queue.Queue = queue.Queue()
        self._stderr: list[str] = []
        self.last_event: dict | None = None
        self.cancelled = False

    def start(self) -> "WorkerJob":
        kwargs = {}
        if os.name == "posix":
            kwargs["start_new_session"] = True     # a Ctrl+C in Blender's terminal is not a cancel
        # errors="replace": a stray non-UTF-8 byte (a library printing) must not end the reader.
        self.proc = subprocess.Popen(self.cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                                     errors="replace", env=child_env(), bufsize=1, **kwargs)
        threading.Thread(target=self._read_stdout, daemon=True).start()
        threading.Thread(target=self._read_stderr, daemon=True).start()
        return self

    def _read_stdout(self):
        # This thread must outlive any line: if it stopped, the worker would
        # block on a full pipe and the bake would hang (read_event never raises).
        try:
            for line in self.proc.stdout:
                line = line.strip()
                if not line:
                    continue
                e = read_event(line)
                if e is not None:
                    self._events.put(e)
                else:
                    self._stderr.append(line[:2000])
                    del self._stderr[:-40]
        finally:
            self._events.put(None)                 # end of stream

    def _read_stderr(self):
        for line in self.proc.stderr:
            self._stderr.append(line.rstrip())
            del self._stderr[:-40]

    def events(self, timeout: float | None = None) -> list:
        """Events so far (blocks up to ``timeout`` for the first one); None marks the end."""
        out = []
        try:
            out.append(self._events.get(timeout=timeout) if timeout else self._events.get_nowait())
            while True:
                out.append(self._events.get_nowait())
        except queue.Empty:
            pass
        for e in out:
            if e is not None:
                self.last_event = e
        return out

    def cancel(self):
        self.cancelled = True
        if self.proc is not None and self.proc.poll() is None:
            if os.name == "posix":
                self.proc.send_signal(signal.SIGTERM)
            else:
                self.proc.terminate()

    def kill(self):
        if self.proc is not None and self.proc.poll() is None:
            self.proc.kill()

    def wait(self, timeout: float | None = None) -> int:
        return self.proc.wait(timeout=timeout)

    @property
    def returncode(self):
        return None if self.proc is None else self.proc.poll()

    def stderr_tail(self) -> str:
        return "\n".join(self._stderr[-10:])
