"""Pure mathematics for lidarcam: rotations, rigid transforms, planes, camera and board models.

Nothing here reads or writes files, and nothing here imports ``estimators``.
Conventions (docs/reference/calibration_json.md): ``T_a_b`` maps points from frame b into frame a, ``p_a = R p_b + t``;
tangent vectors are ``[rotation; translation]`` with right perturbation ``T (+) xi = T Exp(xi)`` (GTSAM's).
"""
