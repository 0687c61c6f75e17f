"""Projector output: one borderless fullscreen pyglet window per projector.

Each projector is an X screen (a RandR output) of the desktop.  Its pattern
image must land on the panel 1:1: no scaling, no filtering, integer offsets.
pyglet is known to place fullscreen windows on the wrong monitor on some
systems and its screen order need not match the desktop's (pyglet issues 763,
1330, 1246), so every window is placed explicitly at its screen's position and
its real X11 geometry is read back and checked before anything is shown.

Threading: pyglet keeps the MAIN thread.  :meth:`ProjectorWindows.open`,
:meth:`~ProjectorWindows.run` and :meth:`~ProjectorWindows.close` are called
there; worker threads (capture, calibration) only call
:meth:`~ProjectorWindows.show` and :meth:`~ProjectorWindows.wait_presented`,
which hand images over under a lock and wake the pyglet loop with a posted
event (no polling).

pyglet is imported lazily, on first use, because importing it opens the X
display named by ``DISPLAY``.
"""

from __future__ import annotations

import ctypes
import os
import sys
import threading
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from lightflow.app.core.errors import DriverError
from lightflow.drivers.base import PatternOutput

#: how a projector's screen is chosen: its 0-based index in :func:`list_screens`, or its name
ScreenSelector = int | str


@dataclass(frozen=True)
class ScreenInfo:
    """One screen (monitor, projector) of the X display, in pyglet's order.

    Attributes
    ----------
    index : int
        0-based position in :func:`list_screens` (what ``--screens`` takes).
    name : str
        RandR output name (``DUMMY0``, ``HDMI-1``), or ``screenN`` if the
        server gives none.
    x, y, width, height : int
        Position and size on the desktop (root window) in pixels.
    """

    index: int
    name: str
    x: int
    y: int
    width: int
    height: int

    @property
    def geometry(self) -> str:
        """X11 geometry string ``WxH+X+Y``."""
        return f"{self.width}x{self.height}+{self.x}+{self.y}"

    def describe(self) -> str:
        """Short human-readable description, e.g. ``screen 1 (DUMMY1 1280x800+1280+0)``."""
        return f"screen {self.index} ({self.name} {self.geometry})"


# ----------------------------------------------------------------------------- pyglet access


def _pyglet():
    """Import pyglet with the options a projector needs (before any window exists)."""
    import pyglet

    if "pyglet.window" not in sys.modules:
        # the hidden shadow window would open $DISPLAY even when another display is asked for
        pyglet.options.shadow_window = False
        # a projector pixel is a panel pixel: no desktop DPI scaling
        pyglet.options.dpi_scaling = "real"
    return pyglet


def _open_display(display: str | None):
    """The pyglet display object for ``display`` (``None``: ``$DISPLAY``)."""
    pyglet = _pyglet()
    from pyglet.display.xlib import NoSuchDisplayException

    name = display or os.environ.get("DISPLAY")
    if not name:
        raise DriverError("X display: DISPLAY is not set and no display was given (e.g. :0)")
    try:
        if display is None:
            return pyglet.display.get_display()
        return pyglet.display.Display(name=display)
    except NoSuchDisplayException:
        raise DriverError(f"X display {name}: cannot connect (is the X server running?)") from None


def _screens(pdisplay) -> list[tuple[ScreenInfo, Any]]:
    out = []
    for i, s in enumerate(pdisplay.get_screens()):
        name = getattr(s, "name", None) or f"screen{i}"
        out.append((ScreenInfo(i, name, s.x, s.y, s.width, s.height), s))
    return out


def list_screens(display: str | None = None) -> list[ScreenInfo]:
    """The screens of an X display in pyglet's order.

    Parameters
    ----------
    display : str, optional
        X display name such as ``":1"``; default ``$DISPLAY``.

    Returns
    -------
    list of ScreenInfo
        Index 0 first; this order is what ``lightflow devices`` prints and
        ``--screens`` uses.

    Raises
    ------
    DriverError
        If the display cannot be opened.
    """
    return [info for info, _ in _screens(_open_display(display))]


def resolve_screen(selector: ScreenSelector, screens: Sequence[ScreenInfo], display=None):
    """Pick a screen by index (int or digit string) or by name.

    Raises
    ------
    DriverError
        Naming the selector and listing the available screens.
    """
    if isinstance(selector, str) and selector.strip().isdigit():
        selector = int(selector.strip())
    for s in screens:
        if (isinstance(selector, int) and s.index == selector) or (
            isinstance(selector, str) and s.name == selector
        ):
            return s
    avail = ", ".join(f"{s.index}={s.name} {s.geometry}" for s in screens) or "none"
    raise DriverError(
        f"X display {display or os.environ.get('DISPLAY')}: no screen {selector!r} "
        f"(available: {avail})"
    )


def _x11_geometry(window) -> tuple[int, int, int, int]:
    """Where the window's GL drawable really is: ``(x, y, width, height)`` in root coordinates.

    Asks the X server, not pyglet's bookkeeping.  pyglet's xlib window draws
    into a child ``_view`` of its top-level ``_window``; that child is what
    must cover the panel.
    """
    from pyglet.libs.x11 import xlib

    xd = window._x_display  # noqa: SLF001 - no public handle to the X connection
    view = window._view  # noqa: SLF001
    xlib.XSync(xd, False)
    attrs = xlib.XWindowAttributes()
    xlib.XGetWindowAttributes(xd, view, ctypes.byref(attrs))
    x, y, child = ctypes.c_int(), ctypes.c_int(), xlib.Window()
    root = xlib.XRootWindow(xd, window.display.x_screen)
    xlib.XTranslateCoordinates(
        xd, view, root, 0, 0, ctypes.byref(x), ctypes.byref(y), ctypes.byref(child)
    )
    return x.value, y.value, attrs.width, attrs.height


# ----------------------------------------------------------------------------- windows


class _Slot:
    """One projector's window and the image hand-over between threads."""

    def __init__(self, name: str, selector: ScreenSelector, image: np.ndarray):
        self.name = name
        self.selector = selector
        self.shape = image.shape
        self.screen: ScreenInfo | None = None
        self.window = None
        self.texture = None
        # guarded by ProjectorWindows._cond
        self.pending: np.ndarray | None = image
        self.current = image  # last presented, shown again if the windows are re-opened
        self.requested = 1
        self.presented = 0


def _check_image(name: str, image: np.ndarray) -> np.ndarray:
    image = np.asarray(image)
    if image.dtype != np.uint8 or image.ndim != 3 or image.shape[2] != 3:
        raise DriverError(
            f"projector {name!r}: expected an RGB uint8 image (height, width, 3), "
            f"got {image.dtype} {image.shape}"
        )
    return image


class ProjectorWindows(PatternOutput):
    """Borderless fullscreen windows showing each projector's image 1:1.

    Parameters
    ----------
    outputs : sequence of (str, int or str, numpy.ndarray)
        One ``(projector name, screen selector, image)`` per projector.  The
        selector is an index into :func:`list_screens` or a screen name; the
        image is RGB ``uint8`` ``(height, width, 3)`` at projector resolution
        (a single projector shows both its patterns in one image).
    display : str, optional
        X display, default ``$DISPLAY``.
    allow_size_mismatch : bool
        If a screen is larger than its image, draw the image 1:1 at the
        top-left and black elsewhere instead of refusing.
    vsync : bool
        Swap on vertical blank so that a camera never sees half of two patterns.

    Examples
    --------
    On the main thread::

        out = ProjectorWindows([("left", 0, img_l), ("right", "HDMI-2", img_r)])
        with out:
            out.run(stop)          # worker threads call out.show(...) meanwhile
    """

    def __init__(
        self,
        outputs: Sequence[tuple[str, ScreenSelector, np.ndarray]],
        *,
        display: str | None = None,
        allow_size_mismatch: bool = False,
        vsync: bool = True,
    ):
        if not outputs:
            raise DriverError("projector windows: no projector given")
        self._slots: dict[str, _Slot] = {}
        for name, selector, image in outputs:
            if name in self._slots:
                raise DriverError(f"projector {name!r}: given twice")
            self._slots[name] = _Slot(name, selector, _check_image(name, image).copy())
        self.display = display
        self.allow_size_mismatch = allow_size_mismatch
        self.vsync = vsync
        self._cond = threading.Condition()
        self._open = False
        self._running = False
        self._waker = None
        self._stop: threading.Event | None = None

    # ------------------------------------------------------------------ main thread

    @property
    def placements(self) -> list[tuple[str, ScreenInfo]]:
        """``(projector name, screen)`` for each projector, after :meth:`open`."""
        return [(s.name, s.screen) for s in self._slots.values()]

    def open(self) -> None:
        """Create, place and verify the windows and show the initial images (main thread).

        Raises
        ------
        DriverError
            If a screen does not exist, is used twice, does not match its
            image's size, or a window did not land exactly on its screen.
        """
        if self._open:
            return
        pdisplay = _open_display(self.display)
        screens = _screens(pdisplay)
        infos = [info for info, _ in screens]
        used: dict[int, str] = {}
        for slot in self._slots.values():
            info = resolve_screen(slot.selector, infos, self.display)
            if info.index in used:
                raise DriverError(
                    f"projector {slot.name!r}: {info.describe()} is already used by "
                    f"projector {used[info.index]!r}"
                )
            used[info.index] = slot.name
            self._check_size(slot, info)
            slot.screen = info
        with self._cond:
            for slot in self._slots.values():
                if slot.pending is None:
                    slot.pending = slot.current
        try:
            self._waker = _make_waker(self)
            for slot in self._slots.values():
                self._create_window(slot, screens[slot.screen.index][1])
            self._open = True
            for slot in self._slots.values():
                self._present(slot)
        except BaseException:
            self._open = True
            self.close()
            raise

    def _check_size(self, slot: _Slot, info: ScreenInfo) -> None:
        h, w = slot.shape[:2]
        where = f"projector {slot.name!r}: image {w}x{h}"
        if w > info.width or h > info.height:
            raise DriverError(
                f"{where} does not fit {info.describe()}; set that output's mode to {w}x{h}"
            )
        if (w, h) != (info.width, info.height) and not self.allow_size_mismatch:
            raise DriverError(
                f"{where} is smaller than {info.describe()}; set that output's mode to "
                f"{w}x{h}, or allow the size mismatch to draw it 1:1 at the top-left"
            )

    def _create_window(self, slot: _Slot, pscreen) -> None:
        pyglet = _pyglet()
        from pyglet import gl

        info = slot.screen
        misplaced = self._place_window(slot, pscreen, override_redirect=False)
        if misplaced:
            # pyglet issue 763: a window manager may put a fullscreen window on
            # another monitor.  An override-redirect window is not managed at all.
            slot.window.close()
            again = self._place_window(slot, pscreen, override_redirect=True)
            if again:
                slot.window.close()
                slot.window = None
                raise DriverError(
                    f"projector {slot.name!r}: window meant for {info.describe()} landed at "
                    f"{misplaced}, and at {again} when bypassing the window manager"
                )
        window = slot.window
        window.switch_to()
        h, w = slot.shape[:2]
        # nearest, no mipmaps: texel centres fall on pixel centres at integer offsets
        slot.texture = pyglet.image.Texture.create(
            w, h, min_filter=gl.GL_NEAREST, mag_filter=gl.GL_NEAREST
        )

        def on_close():
            self._request_stop()
            return True  # keep the window; close() removes it

        def on_expose():
            self._draw(slot)
            return True

        def on_draw():
            # only if some other loop redraws on a timer; Window.draw() flips after this
            self._render(slot)
            return True

        window.push_handlers(on_close=on_close, on_expose=on_expose, on_draw=on_draw)

    def _place_window(self, slot: _Slot, pscreen, override_redirect: bool) -> str:
        """Create and map the slot's window on its screen; describe the misplacement, or ''."""
        from pyglet.libs.x11 import xlib
        from pyglet.window import Window

        info = slot.screen
        # Created hidden, moved onto the screen, then mapped: a window manager
        # puts a fullscreen window on the monitor where it already is.
        window = Window(
            fullscreen=True,
            screen=pscreen,
            style=Window.WINDOW_STYLE_BORDERLESS,
            caption=f"lightflow projector {slot.name}",
            vsync=self.vsync,
            visible=False,
        )
        slot.window = window
        if override_redirect:
            attrs = xlib.XSetWindowAttributes()
            attrs.override_redirect = True
            xlib.XChangeWindowAttributes(
                window._x_display,  # noqa: SLF001 - pyglet has no public handle for this
                window._window,  # noqa: SLF001
                xlib.CWOverrideRedirect,
                ctypes.byref(attrs),
            )
        window.set_location(info.x, info.y)
        window.set_mouse_visible(False)
        window.set_visible(True)
        window.activate()  # keyboard focus for Esc (a window manager would not give it)
        return self._misplacement(slot)

    def _misplacement(self, slot: _Slot) -> str:
        """'' if the window covers exactly its screen, else where it really is.

        Asks the X server (where the GL drawable is in root coordinates) and
        pyglet (location, size, framebuffer size); all must agree.
        """
        info, window = slot.screen, slot.window
        want = (info.x, info.y, info.width, info.height)
        got = _x11_geometry(window)
        loc, size = window.get_location(), window.get_size()
        fb = window.get_framebuffer_size()
        if got == want and loc == (info.x, info.y) and size == fb == (info.width, info.height):
            return ""
        gx, gy, gw, gh = got
        return (
            f"{gw}x{gh}+{gx}+{gy} (pyglet: location {loc[0]},{loc[1]}, size {size[0]}x{size[1]}, "
            f"framebuffer {fb[0]}x{fb[1]})"
        )

    def _render(self, slot: _Slot) -> None:
        """Draw the slot's texture into the back buffer: 1:1 at the top-left, black elsewhere."""
        from pyglet import gl

        window = slot.window
        window.switch_to()
        gl.glDisable(gl.GL_BLEND)
        gl.glClearColor(0.0, 0.0, 0.0, 1.0)
        window.clear()
        # GL's origin is bottom-left: the image's top row goes to the screen's top row
        slot.texture.blit(0, window.get_framebuffer_size()[1] - slot.shape[0])

    def _draw(self, slot: _Slot) -> None:
        """Render, flip, and return once the X server has the new frame."""
        from pyglet import gl

        window = slot.window
        self._render(slot)
        window.flip()
        # wait until the swap really happened, and the X server has it
        gl.glFinish()
        from pyglet.libs.x11 import xlib

        xlib.XSync(window._x_display, False)  # noqa: SLF001

    def _upload(self, slot: _Slot, image: np.ndarray) -> None:
        from pyglet import gl

        slot.window.switch_to()
        h, w = image.shape[:2]
        rows = np.ascontiguousarray(image[::-1])  # GL rows run bottom-up
        slot.texture.bind()
        gl.glPixelStorei(gl.GL_UNPACK_ALIGNMENT, 1)
        gl.glTexSubImage2D(
            gl.GL_TEXTURE_2D, 0, 0, 0, w, h, gl.GL_RGB, gl.GL_UNSIGNED_BYTE, rows.ctypes.data
        )

    def _present(self, slot: _Slot) -> None:
        """Upload the pending image (if any), draw and flip; then mark it presented."""
        with self._cond:
            image, seq = slot.pending, slot.requested
            slot.pending = None
        if image is None:
            return
        self._upload(slot, image)
        self._draw(slot)
        with self._cond:
            slot.current = image
            slot.presented = max(slot.presented, seq)
            self._cond.notify_all()

    def _on_wake(self) -> None:
        if not self._open:
            return
        for slot in self._slots.values():
            self._present(slot)
        if self._stop is not None and self._stop.is_set():
            import pyglet

            pyglet.app.exit()

    def _request_stop(self) -> None:
        if self._stop is not None:
            self._stop.set()
        import pyglet

        pyglet.app.exit()

    def run(
        self,
        stop: threading.Event,
        tick: Callable[[float], None] | None = None,
        tick_interval: float = 0.1,
    ) -> None:
        """Run the pyglet loop on the main thread until ``stop`` is set.

        Closing a window or pressing Esc sets ``stop`` too, so that the worker
        threads waiting on it end.

        Parameters
        ----------
        stop : threading.Event
            Set by anyone to end the loop; always set when this returns.
        tick : callable, optional
            Called as ``tick(dt)`` on the main thread every ``tick_interval``
            seconds (e.g. to update a status line); an exception ends the loop
            and propagates.
        tick_interval : float
            Seconds between ticks.
        """
        if not self._open:
            raise DriverError("projector windows: run() before open()")
        import pyglet

        self._stop = stop
        # wakes the loop when `stop` is set from elsewhere; stop.wait() blocks, it does not poll
        watcher = threading.Thread(
            target=self._watch, args=(stop,), name="projector-stop", daemon=True
        )
        watcher.start()
        if tick is not None:
            pyglet.clock.schedule_interval(tick, tick_interval)
        self._running = True
        try:
            # posted before the loop starts: a stop set meanwhile is seen on the first step
            pyglet.app.platform_event_loop.post_event(self._waker, "on_wake")
            pyglet.app.run(None)  # None: draw only when an image changes or is exposed
        finally:
            self._running = False
            stop.set()
            watcher.join()
            if tick is not None:
                pyglet.clock.unschedule(tick)
            with self._cond:
                self._cond.notify_all()

    def _watch(self, stop: threading.Event) -> None:
        stop.wait()
        import pyglet

        pyglet.app.platform_event_loop.post_event(self._waker, "on_wake")

    def close(self) -> None:
        """Close all windows (main thread).  Safe to call twice."""
        if not self._open:
            return
        self._open = False
        for slot in self._slots.values():
            if slot.texture is not None and slot.window is not None:
                slot.window.switch_to()
                slot.texture.delete()
            slot.texture = None
            if slot.window is not None:
                slot.window.close()
            slot.window = None
        with self._cond:
            self._cond.notify_all()

    # ------------------------------------------------------------------ any thread

    def show(self, projector: str, image: np.ndarray) -> None:
        """Replace one projector's image (thread-safe; returns at once).

        Parameters
        ----------
        projector : str
            Projector name as given to the constructor.
        image : numpy.ndarray
            RGB ``uint8`` image of the same size as the initial one.  It is
            copied, so the caller may reuse its buffer.

        Raises
        ------
        DriverError
            Unknown projector or wrong image size.
        """
        slot = self._slots.get(projector)
        if slot is None:
            raise DriverError(
                f"projector {projector!r}: unknown (have {', '.join(self._slots)})"
            )
        image = _check_image(projector, image)
        if image.shape != slot.shape:
            raise DriverError(
                f"projector {projector!r}: image is {image.shape[1]}x{image.shape[0]}, "
                f"expected {slot.shape[1]}x{slot.shape[0]}"
            )
        with self._cond:
            slot.pending = image.copy()
            slot.requested += 1
        if self._waker is not None:
            import pyglet

            pyglet.app.platform_event_loop.post_event(self._waker, "on_wake")

    def wait_presented(self, timeout: float | None = None, projector: str | None = None) -> bool:
        """Wait until every image shown so far has been drawn and flipped.

        Parameters
        ----------
        timeout : float, optional
            Seconds; ``None`` waits for ever.
        projector : str, optional
            Wait only for this projector.

        Returns
        -------
        bool
            ``True`` once presented, ``False`` on timeout.

        Raises
        ------
        DriverError
            If the windows were closed or the loop ended before that.
        """
        slots = [self._slots[projector]] if projector else list(self._slots.values())
        with self._cond:
            targets = [(s, s.requested) for s in slots]

            def done() -> bool:
                return all(s.presented >= want for s, want in targets)

            def dead() -> bool:
                stopped = self._stop is not None and self._stop.is_set() and not self._running
                return not self._open or stopped

            ok = self._cond.wait_for(lambda: done() or dead(), timeout)
            if done():
                return True
            if ok:
                names = ", ".join(s.name for s in slots)
                raise DriverError(
                    f"projector {names}: windows closed before the new image was shown"
                )
            return False


def _make_waker(owner: ProjectorWindows):
    """An event dispatcher that runs ``owner._on_wake`` on the pyglet (main) thread."""
    import pyglet

    class _Waker(pyglet.event.EventDispatcher):
        def on_wake(self):
            owner._on_wake()

    _Waker.register_event_type("on_wake")
    return _Waker()
