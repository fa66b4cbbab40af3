"""Scene description: Camera, PointLight, PhongMaterial, Floor, SceneObject, Scene.

A :class:`Scene` is plain data. It converts to the renderer contract
(:meth:`Scene.params`, a flat mapping of named arrays) and to and from Mitsuba
XML. The XML files are genuine Mitsuba scenes (``mi.load_file`` renders them
with the project's ``phong`` BSDF and ``phong_integrator``); the object's knobs are ``<default>``
values at the top of the file, so a person edits them by hand, or overrides them
like Mitsuba's ``-D name=value``.
"""
from __future__ import annotations

from .model import (COLOURS, MATERIALS, OBJECT_DEFAULTS, SIZES, Camera, Floor, PhongMaterial, PointLight, Scene,
                    SceneObject, colour_rgb, fmt, object_overrides)
from .xml import load_scene, save_scene, scene_to_xml

__all__ = ["COLOURS", "MATERIALS", "OBJECT_DEFAULTS", "SIZES", "Camera", "Floor", "PhongMaterial", "PointLight",
           "Scene", "SceneObject", "colour_rgb", "fmt", "load_scene", "object_overrides", "save_scene",
           "scene_to_xml"]
