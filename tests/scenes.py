"""Small analytic test scenes: spheres on a ring of cameras (see shadowcorr.synth.spheres)."""

from shadowcorr.poses import look_at_pose as look_at
from shadowcorr.synth.spheres import render_spheres, sphere_scene

__all__ = ["look_at", "render_spheres", "sphere_scene"]
