"""The live meshcat viewer: a meshcat server in a child process that exits with its owner."""

from __future__ import annotations

import contextlib
import io
import os
import select
import subprocess
import sys
import threading
import time
import warnings
import weakref
from collections.abc import Iterable, Sequence

import numpy as np
import pinocchio as pin

with warnings.catch_warnings():
    # meshcat 0.3.2 imports pyzmq's deprecated zmq.eventloop.ioloop; nothing we can act on.
    warnings.simplefilter("ignore", DeprecationWarning)
    import meshcat

from m3t1r.app.scene import DEFAULT_CAMERA, Camera, MachineView, ViewerError, _Lowered
from m3t1r.app.static_page import build_scene

__all__ = ["LiveViewer", "open_viewer"]

_SERVER_START_TIMEOUT = 20.0  # [s] a first import of tornado/zmq on a cold disk is slow
_SERVER_STOP_TIMEOUT = 5.0  # [s]


# --------------------------------------------------------------------------------------------
# Live viewer
# --------------------------------------------------------------------------------------------


class LiveViewer:
    """A meshcat server process showing a scene, and the client connected to it.

    Owns the process: `close()` (or leaving the `with` block, or garbage collection, or
    interpreter exit) stops it. `url` is the page to open in a browser.
    """

    def __init__(self, process: subprocess.Popen, url: str, visualizer: meshcat.Visualizer) -> None:
        self.process = process
        self.url = url
        self.visualizer = visualizer
        self._finalizer = weakref.finalize(self, _stop_server, process, visualizer)

    @property
    def pid(self) -> int:
        return self.process.pid

    def wait(self, poll: float = 0.5) -> None:
        """Block until Ctrl-C or the server process ends, then stop the server."""
        try:
            while self.process.poll() is None:
                time.sleep(poll)
        except KeyboardInterrupt:
            pass
        finally:
            self.close()

    def close(self) -> None:
        """Stop the server process and close the client socket (idempotent)."""
        self._finalizer()

    def __enter__(self) -> "LiveViewer":
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()


def _stop_server(process: subprocess.Popen, visualizer: meshcat.Visualizer | None) -> None:
    window = getattr(visualizer, "window", None)
    socket = getattr(window, "zmq_socket", None)
    if socket is not None:
        socket.close(linger=0)  # a pending request would otherwise keep the context alive
    if process.poll() is None:
        process.terminate()
        try:
            process.wait(timeout=_SERVER_STOP_TIMEOUT)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()
    for stream in (process.stdout, process.stderr):
        if stream is not None:
            stream.close()


# meshcat's server, plus a watchdog: if we die without stopping it (SIGTERM, SIGKILL), it is
# re-parented, notices within a second and exits, instead of holding its ports forever.
_SERVER_MAIN = """
import os, sys, threading, time
parent = os.getppid()
def watch():
    while os.getppid() == parent:
        time.sleep(1.0)
    os._exit(0)
threading.Thread(target=watch, daemon=True).start()
from meshcat.servers.zmqserver import main
sys.argv = ["meshcat-server"]
main()
"""


def _start_server() -> tuple[subprocess.Popen, str, str]:
    """Start meshcat's server and read its (zmq_url, web_url) announcement.

    Started here rather than by `meshcat.Visualizer()` so that this module owns the process:
    meshcat 0.3.2 only kills it at interpreter exit (its `Visualizer.close()` is broken), pipes
    its stderr without ever reading it (a long session would fill the pipe and hang the server),
    and waits for its announcement with no timeout.
    """
    # Its own session: a Ctrl-C meant for the CLI reaches us, and we stop the server cleanly.
    process = subprocess.Popen(
        [sys.executable, "-u", "-c", _SERVER_MAIN],
        stdin=subprocess.DEVNULL,
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        start_new_session=True,
    )
    announced: dict[str, str] = {}
    pending = b""
    deadline = time.monotonic() + _SERVER_START_TIMEOUT
    assert process.stdout is not None
    descriptor = process.stdout.fileno()
    try:
        while len(announced) < 2:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise ViewerError(f"the meshcat server did not start within {_SERVER_START_TIMEOUT:.0f} s")
            # Raw reads: a buffered readline could swallow both lines while select() waits on the fd.
            ready, _, _ = select.select([descriptor], [], [], remaining)
            if not ready:
                continue
            chunk = os.read(descriptor, 4096)
            if not chunk:
                process.wait(timeout=_SERVER_STOP_TIMEOUT)
                raise ViewerError(
                    f"the meshcat server exited with code {process.returncode} "
                    f"(run `{sys.executable} -m meshcat.servers.zmqserver` to see why)"
                )
            *lines, pending = (pending + chunk).split(b"\n")
            for line in lines:
                key, _, value = line.decode("utf-8", "replace").strip().partition("=")
                if key in ("zmq_url", "web_url") and value:
                    announced[key] = value
    except BaseException:
        _stop_server(process, None)
        raise
    # Anything it prints later must not fill the pipe and block it.
    threading.Thread(target=_drain, args=(process.stdout,), daemon=True).start()
    return process, announced["zmq_url"], announced["web_url"]


def _drain(stream: io.BufferedReader) -> None:
    with contextlib.suppress(OSError, ValueError):
        while stream.read(4096):
            pass


def open_viewer(
    views: Sequence[MachineView],
    pose: Sequence[float] | None = None,
    sliders: Sequence[float] | None = None,
    markers: Iterable[pin.SE3] | np.ndarray | None = None,
    camera: Camera | None = DEFAULT_CAMERA,
    magnification: float | None = None,
) -> LiveViewer:
    """Start a meshcat server, draw the scene in it, and return it (url, visualizer, close()).

    The scene is solved and recorded before the server starts, so a bad command starts nothing.
    Use as `with open_viewer(views) as live: print(live.url); live.wait()`. magnification: as in
    `build_scene` (the deviation of every machine after the first from it, drawn this many times;
    None: chosen from the scene).

    Raises what `build_scene` raises, and ViewerError when the server does not come up.
    """
    recording = build_scene(
        views, pose=pose, sliders=sliders, markers=markers, camera=camera, magnification=magnification
    )
    process, zmq_url, web_url = _start_server()
    try:
        with contextlib.redirect_stdout(io.StringIO()):  # meshcat prints the URL; the caller decides
            visualizer = meshcat.Visualizer(zmq_url=zmq_url)
        live = LiveViewer(process, web_url, visualizer)
    except BaseException:
        _stop_server(process, None)
        raise
    try:
        for message in recording.window.messages:
            visualizer.window.send(_Lowered(message))
    except BaseException:
        live.close()
        raise
    return live
