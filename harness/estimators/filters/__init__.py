"""The paper's density and gradient filters on the grid (eqs. ``density filter``,
``density Riccati``, ``gradient filter``, ``gradient Riccati``): a dense reference
form (:mod:`.reference`) and a fast form with local covariances (:mod:`.local`), whose
gradient update solves a weighted Poisson problem (:mod:`.poisson`; on free space
:mod:`harness.estimators.filters.free_poisson`).
"""
