"""From per-frame observations to the extrinsic and its uncertainty: the closed form (``closed_form``), the 2D
minimal solver and the choice among its solutions (``minimal_solver``, ``solution_selection``), the factor graph
(``factors``, ``refinement``), the emcee posterior (``posterior``), and the generative model with its
Cramer-Rao bound (``observation_model``).

May import: ``geometry``, ``estimators.errors``, ``estimators.measurements``, ``camera``, ``lidar``,
``simulation`` (the observation model casts rays on its scenes) and its own modules; never ``io``, ``analysis``,
the pipeline or the CLI.
"""
