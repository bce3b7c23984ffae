"""Linear SfM (paper §3.3): camera translations and line depths from colinearity and coplanarity.

Unknowns (paper §3.3 "Model"): the camera centres ``T_i`` and one depth ``lambda`` per line
observation -- the segment mid-point ``P = T_i + lambda D`` along its unit world viewing ray
``D = R_wc K^-1 x~``. Rotations (``pre.R_wc``) and the Manhattan directions are known, so the
colinearity and coplanarity constraints are linear, and the depths must be positive.

:func:`solve_linear` (:mod:`.solve`) runs the steps; each module's docstring says its part of the
formulation and where it departs from the paper:

* :mod:`.baseline` -- does the spin show parallax at all (zero baseline: one shared centre)?
* :mod:`.system` -- the observations, the usable relations, the unknowns in Manhattan coordinates
  and the system's rows (colinearity, coplanarity, floor), the depths eliminated;
* :mod:`.priors` -- the body-motion prior and the spin model (not in the paper);
* :mod:`.registration` -- which frames the lines determine (the others are not solved);
* :mod:`.scale` -- the gauge, and the units the solution is given in;
* :mod:`.robust` -- the depth bound (active set) and the reweighted relations (IRLS);
* :mod:`.result` -- camera centres, one 3D line per track, the residual report.
"""
from .registration import (
    REASON_BUNDLE_ADJUST,
    UNREGISTERED_REASONS,
    bridged_frames,
    motion_links,
    reason_counts,
    register_frames,
    weak_axes,
)
from .solve import floor_verified, solve_linear
from .system import observation_rays

__all__ = [
    "REASON_BUNDLE_ADJUST",
    "UNREGISTERED_REASONS",
    "bridged_frames",
    "floor_verified",
    "motion_links",
    "observation_rays",
    "reason_counts",
    "register_frames",
    "solve_linear",
    "weak_axes",
]
