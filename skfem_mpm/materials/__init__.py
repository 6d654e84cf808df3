"""Constitutive models, one file each; the interface is
:class:`~skfem_mpm.materials.base.Material`.

Write your own by following the same shape (see examples/custom_material.py);
give it a compiled ``point_update`` (:func:`point_update`) and the compiled
executor runs it without leaving compiled code (a finite-strain material's
adaptive steps need a compiled ``point_wave_speed`` too: :func:`point_wave_speed`); declare per-particle state
(``particles.state[name]``) with ``state_fields`` (:mod:`.state`).
"""
from .base import Material, det, incremental_deformation, lame_parameters
from .bbar import BBar
from .compiled import point_update, point_wave_speed
from .drucker_prager import DruckerPrager
from .linear_elastic import LinearElastic
from .mohr_coulomb import MohrCoulomb
from .neo_hookean import NeoHookean
from .state import StateLayout, state_layout
from .von_mises import VonMises

__all__ = ["Material", "LinearElastic", "NeoHookean", "MohrCoulomb", "DruckerPrager",
           "VonMises", "BBar", "lame_parameters", "det",
           "incremental_deformation", "point_update", "point_wave_speed", "state_layout", "StateLayout"]
