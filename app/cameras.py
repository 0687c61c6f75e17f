"""Open any camera from a URI-like string (``aravis:...``, ``v4l2:...``, ...).

The command line and the calibration code name cameras this way so that
hardware, simulation and recordings are interchangeable everywhere.
"""

from __future__ import annotations

from typing import Any

from lightflow.app.core.errors import ConfigError
from lightflow.drivers.base import Camera

#: the accepted forms, shown in every error about a camera URI
FORMS = (
    "aravis:ID|ADDRESS (GigE/USB3 Vision camera)",
    "v4l2:/dev/videoN (V4L2 device)",
    "synthetic:SCENE (rendered scene, needs a rig)",
    "replay:REC (a recording folder)",
)
SCHEMES = ("aravis", "v4l2", "synthetic", "replay")


def _forms() -> str:
    return "; ".join(FORMS)


def _pick(opts: dict[str, Any], uri: str, allowed: tuple[str, ...]) -> dict[str, Any]:
    """The options that apply to this scheme (None means "driver default")."""
    unknown = sorted(set(opts) - set(allowed))
    if unknown:
        raise ConfigError(
            f"camera {uri!r}: option {unknown[0]!r} does not apply "
            f"(accepted: {', '.join(allowed) or 'none'})"
        )
    return {k: v for k, v in opts.items() if v is not None}


def open_camera(uri: str, rig=None, **opts: Any) -> Camera:
    """Create the :class:`~lightflow.drivers.base.Camera` a URI names (not yet opened).

    Parameters
    ----------
    uri : str
        ``aravis:ID|ADDRESS``, ``v4l2:/dev/videoN``, ``synthetic:SCENE`` or ``replay:REC``.
    rig : Rig, optional
        Needed by ``synthetic:`` (the rig the scene is rendered with); for
        ``replay:`` it overrides the recording's embedded rig.
    **opts
        Driver options; ``None`` values mean the driver default.  ``synthetic``:
        frames, fps, exposure_s, seed, realtime.  ``replay``: loop, realtime.
        ``aravis``: pixel_format, n_buffers, lost_after_s, probe_timeout_s, control_wait_s.
        ``v4l2``: pixel_format, n_buffers.

    Returns
    -------
    Camera

    Raises
    ------
    ConfigError
        For an unknown scheme or an empty target, naming the URI and the accepted forms.

    Examples
    --------
    >>> cam = open_camera("synthetic:board", rig, frames=20)   # doctest: +SKIP
    >>> with cam:                                               # doctest: +SKIP
    ...     for frame in cam.frames(): ...
    """
    scheme, sep, target = str(uri).partition(":")
    if not sep or scheme not in SCHEMES:
        raise ConfigError(f"camera {uri!r}: unknown camera URI (expected one of: {_forms()})")
    if not target:
        raise ConfigError(f"camera {uri!r}: nothing after '{scheme}:' (expected {_forms()})")
    if scheme == "aravis":
        from lightflow.drivers.aravis import AravisCamera

        kw = _pick(opts, uri, ("pixel_format", "n_buffers", "lost_after_s", "probe_timeout_s",
                               "control_wait_s"))
        return AravisCamera(target, **kw)
    if scheme == "v4l2":
        from lightflow.drivers.v4l2 import V4L2Camera

        return V4L2Camera(target, **_pick(opts, uri, ("pixel_format", "n_buffers")))
    if scheme == "synthetic":
        from lightflow.drivers.sim.synthetic import SyntheticCamera

        if rig is None:
            raise ConfigError(f"camera {uri!r}: a synthetic camera needs a rig (--rig RIG)")
        kw = _pick(opts, uri, ("frames", "fps", "exposure_s", "seed", "realtime"))
        if "frames" in opts and opts["frames"] is None:
            kw["frames"] = None  # endless, not the driver's default of 10
        return SyntheticCamera(rig, target, **kw)
    from lightflow.app.replay_camera import RecordedCamera

    return RecordedCamera(target, rig=rig, **_pick(opts, uri, ("loop", "realtime")))
