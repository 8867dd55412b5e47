"""Minimal (and non-minimal) solvers: pure functions on arrays, one module per solver, named
after its function (import from the module: ``from planarloc.solvers.relpose_planar_2p import
relpose_planar_2p``; the package does not re-export them, so module and function names never
shadow each other).

=========================  =====================================================================
module                     solver
=========================  =====================================================================
``relpose_planar_2p``      planar 2-point essential matrix (paper Sec. IV-A), batched variant
``relpose_5p_nister``      5-point, Nistér 2004 (baseline)
``relpose_5p_stewenius``   5-point, Stewénius, Engels, Nistér 2006 (baseline)
``relpose_8p``             normalized 8-point (baseline)
``abspose_2p2p``           query pose from two relative poses (eq. 12-15)
``abspose_2p1p``           query pose from one relative pose and one match (eq. 16-18)
``abspose_up2p``           upright 2-point absolute pose from 2D-3D (structure mode)
=========================  =====================================================================

Relative poses are ``ref_from_query`` (``x_ref = R x_query + t``, ``x_refᵀ E x_query = 0``);
absolute poses are the query's ``cam_from_world``. Every solver returns all real solutions
that pass the stated checks (an empty list on degenerate input).
"""
