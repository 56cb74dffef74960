"""The built-in scenes: the paper's first experiment (three boxes on an oval table), the
loop world (two laps round a block of textured walls, :mod:`eifslam.sim.scene.loop`) and
the aliasing scene (one lap round a block whose walls repeat the same photographs,
:mod:`eifslam.sim.scene.aliasing`).

Pure parts (importing them loads neither OpenCV nor matplotlib):
:func:`make_scene`, :func:`make_loop_scene`, :func:`make_aliasing_scene`,
:class:`BuiltinScene`, :class:`Box`, :func:`estimate_box_ratio`, and :func:`same_place`
(whether two frames see the same place, :mod:`eifslam.sim.scene.places`).
Rendering (:func:`render_frame`, :func:`render_scene`) uses OpenCV and is imported lazily,
on first access.

>>> from eifslam.sim.scene import make_scene
>>> scene = make_scene(n_frames=54)
>>> scene.positions.shape, scene.quats_wxyz.shape
((54, 3), (54, 4))
"""

from __future__ import annotations

from typing import Any

from .boxes import RectangleFit, estimate_box_ratio, fit_rectangle, top_face_mask
from .layout import Box, BuiltinScene, Surface, make_scene
from .aliasing import AliasingScene, make_aliasing_scene
from .loop import make_loop_scene
from .places import same_place

__all__ = [
    "Box",
    "BuiltinScene",
    "Surface",
    "make_scene",
    "make_loop_scene",
    "make_aliasing_scene",
    "AliasingScene",
    "same_place",
    "estimate_box_ratio",
    "fit_rectangle",
    "top_face_mask",
    "RectangleFit",
    "render_frame",
    "render_scene",
]


def __getattr__(name: str) -> Any:
    """Lazy access to the OpenCV-based renderer."""
    if name in ("render_frame", "render_scene"):
        from . import render

        return getattr(render, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
