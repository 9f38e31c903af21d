"""Analyses built on the layers below (thesis chapters 2, 4 and 7).

- :mod:`.cw`: closed-form Clohessy-Wiltshire propagation and state-transition matrix;
- :mod:`.coupled`: the simplified coupled feature-point model (the package's) and the fully
  coupled Segal-Gurfil model (thesis eqs. 2.40-2.42, misprints corrected), batched;
- :mod:`.dynamics_study`: the studies of thesis section 2.5 as figures and tables
  (``spmc dynamics``);
- :mod:`.observability`: Hermann-Krener rank test and the filter-state observability Gramian
  (``spmc observability``);
- :mod:`.mass_properties`: mass properties of a closed mesh (``spmc inertia``);
- :mod:`.sensitivity`: what drives the error in a dispersed campaign (Spearman, rank-biserial,
  SALib Sobol indices; ``spmc report``);
- :mod:`.sweep`: grids of whole campaigns (``spmc sweep``).
"""
