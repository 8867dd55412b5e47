"""Minimal (and non-minimal) solvers: pure functions on arrays, one module per solver, named
after its function. The package exposes the functions themselves::

    import planarloc.solvers as S
    S.relpose_planar_2p(xq, xr)            # the function, not the module
    from planarloc.solvers.relpose_planar_2p import relpose_planar_2p   # also works

=========================  =====================================================================
function                   solver
=========================  =====================================================================
``relpose_planar_2p``      planar 2-point essential matrix (paper Sec. IV-A), batched variant
``relpose_5p_nister``      5-point, Nistér 2004 (baseline)
``relpose_5p_stewenius``   5-point, Stewénius, Engels, Nistér 2006 (baseline)
``relpose_8p``             normalized 8-point (baseline)
``abspose_2p2p``           query pose from two relative poses (eq. 12-15)
``abspose_2p1p``           query pose from one relative pose and one match (eq. 16-18)
``abspose_up2p``           upright 2-point absolute pose from 2D-3D (structure mode)
``abspose_p3p``            6DoF three-point absolute pose from 2D-3D (Grunert; structure mode)
=========================  =====================================================================

Relative poses are ``ref_from_query`` (``x_ref = R x_query + t``, ``x_refᵀ E x_query = 0``);
absolute poses are the query's ``cam_from_world``. Every solver returns all real solutions
that pass the stated checks (an empty list on degenerate input).

Single calls validate cheaply: a plain C-contiguous float64 array goes straight into one
compiled kernel that checks the values itself; any other input, and any value it rejects, goes
through :func:`planarloc.geometry.validation.check_array` for the usual one-line message.
Generic numerics (real roots by Sturm sequences, real eigenvalues) live one layer below, in
:mod:`planarloc.numerics`; the five-point machinery shared by Nistér's and Stewénius' solvers
in :mod:`planarloc.solvers._five_point`.

Every submodule is imported here, before the names are bound to the functions: a submodule
imported later would otherwise rebind the package attribute to itself.
"""

from planarloc.solvers import (  # noqa: F401  (load every submodule first, see above)
    abspose_2p1p as _m_abspose_2p1p,
    abspose_2p2p as _m_abspose_2p2p,
    abspose_p3p as _m_abspose_p3p,
    abspose_up2p as _m_abspose_up2p,
    relpose_5p_nister as _m_relpose_5p_nister,
    relpose_5p_stewenius as _m_relpose_5p_stewenius,
    relpose_8p as _m_relpose_8p,
    relpose_planar_2p as _m_relpose_planar_2p,
)
from planarloc.solvers.abspose_2p1p import abspose_2p1p
from planarloc.solvers.abspose_2p2p import abspose_2p2p
from planarloc.solvers.abspose_p3p import abspose_p3p
from planarloc.solvers.abspose_up2p import abspose_up2p
from planarloc.solvers.relpose_5p_nister import (
    essentials_5p_nister,
    relpose_5p_nister,
    relpose_5p_nister_batch,
)
from planarloc.solvers.relpose_5p_stewenius import (
    essentials_5p_stewenius,
    relpose_5p_stewenius,
    relpose_5p_stewenius_batch,
)
from planarloc.solvers.relpose_8p import essential_8p, relpose_8p, relpose_8p_batch
from planarloc.solvers.relpose_planar_2p import relpose_planar_2p, relpose_planar_2p_batch

__all__ = [
    "abspose_2p1p",
    "abspose_2p2p",
    "abspose_p3p",
    "abspose_up2p",
    "essential_8p",
    "essentials_5p_nister",
    "essentials_5p_stewenius",
    "relpose_5p_nister",
    "relpose_5p_nister_batch",
    "relpose_5p_stewenius",
    "relpose_5p_stewenius_batch",
    "relpose_8p",
    "relpose_8p_batch",
    "relpose_planar_2p",
    "relpose_planar_2p_batch",
]
