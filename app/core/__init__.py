"""The processing core: ndarrays in, ndarrays out.

Rig and pattern geometry, the lens model, band measurement, the band-profile
model, flows, the depth model and :class:`~lightflow.app.core.pipeline.DepthPipeline`.
Nothing here touches hardware, files of recordings, Rerun or the terminal, and
nothing here imports from the rest of :mod:`lightflow.app` or from
:mod:`lightflow.drivers`: dependencies point one way, into the core.
"""
