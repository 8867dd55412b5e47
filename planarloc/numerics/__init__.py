"""Numerical kernels below the solvers: real roots of polynomials, real eigenvalues, SPD solves.

Layer: ``numerics`` sits beside ``geometry`` at the bottom (numpy and numba only, no
planarloc imports) and is used by ``solvers`` and ``robust``. Nothing here knows about cameras or poses:

=====================  =========================================================================
module                 holds
=====================  =========================================================================
``sturm``              all distinct real roots of a univariate polynomial (Sturm sequences,
                       bisection, Newton safeguarded by bisection); Horner evaluation
``eigen``              real eigenvalues of a small dense nonsymmetric matrix (balancing,
                       Hessenberg reduction, shifted double-step QR ``hqr``)
``cholesky``           Cholesky factor and solves of small symmetric positive-definite matrices
``null_space``         orthonormal null-space basis of a small wide matrix (Householder QR of
                       its transpose): the five-point and minimal 8-point linear steps
``kernel_cache``       where numba keeps the compiled kernels, also on a read-only install (loads
                       the install's warm cache, writes to a user folder or nowhere); imported
                       by ``planarloc/__init__.py`` before any kernel is defined
``user_folders``       this user's folder in the shared temp folder (``planarloc-<uid>``, mode
                       0700, refused if a link or another user's), for the caches
``blas_threads``       how long OpenBLAS's idle threads spin (set before numpy loads, by
                       ``planarloc/__init__.py``) and the stream's hold of BLAS to one thread
=====================  =========================================================================

What is specific to one problem stays with its solver: the eigenvectors of Stewénius' action
matrix (:func:`planarloc.solvers.relpose_5p_stewenius.action_eigenvector`) use the structure of
its monomial basis, and the five-point polynomial system lives in
:mod:`planarloc.solvers._five_point`.

All functions are numba kernels on validated, finite input: they return counts or success
flags instead of raising, so that a batched caller never aborts a batch for one bad sample.
After editing a kernel here, delete the ``*.nbi``/``*.nbc`` files under
``planarloc/solvers/__pycache__`` too (numba's cache does not track calls across modules).
"""
