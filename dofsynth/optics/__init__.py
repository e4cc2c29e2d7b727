"""Optics: the circle of confusion (`coc`), aperture shapes (`aperture`, a registry of kinds)
and their anti-aliased blur kernels (`kernel`). Pure maths on numpy; nothing else of dofsynth."""
from dofsynth.optics.aperture import APERTURES, Aperture, Disk, Polygon, aperture_from_dict, parse_aperture
from dofsynth.optics.coc import coc_radius
from dofsynth.optics.kernel import coverage, kernel, support_radius

__all__ = ["APERTURES", "Aperture", "Disk", "Polygon", "aperture_from_dict", "parse_aperture", "coc_radius",
           "coverage", "kernel", "support_radius"]
