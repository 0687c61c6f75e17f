"""Hardware cameras (Aravis, V4L2) and pattern output (projector windows).

The device interfaces are in :mod:`lightflow.drivers.base`; the simulator is
:mod:`lightflow.drivers.sim`.  :func:`lightflow.app.cameras.open_camera` opens
any camera from its URI.
"""
