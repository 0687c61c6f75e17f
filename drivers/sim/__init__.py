"""The physical simulator: scenes, a renderer and the synthetic camera.

It shares only the core's small types (rig, patterns, frames, errors) with the
reconstruction: its projection is OpenCV's own and its pattern rasterisation
its own, so an error in the core's geometry shows instead of cancelling.
"""
