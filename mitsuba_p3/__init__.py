"""mitsuba-p3: Bayesian inverse graphics for few-shot concept learning.

Scenes (:mod:`mitsuba_p3.scene`) are rendered by the Phong renderers of
:mod:`mitsuba_p3.render`; Mitsuba is imported lazily through
:mod:`mitsuba_p3.backend`, which picks a working libLLVM first.
"""
__version__ = "0.1.0"
