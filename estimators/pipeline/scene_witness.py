"""``calibrate --scene``: the scene's term joined to the boards' graph, a pair folder's camera and 3D LiDAR.

The boards' estimate (planes, edges, range terms: the graph's, or its posterior's) is checked against the scene
(``scene_check.check_scene``, the board left out so that the scene is a witness independent of the boards): the
scene's estimate near it (the minimum sought from the boards' estimate unless another fits the scene significantly
better, ``scene_alignment.nearest_decided``), with its covariance (the blocks' sandwich plus the scatter of minima
as low).

The scene's term is its translation along the boards' weak direction (their largest translation standard
deviation, in the camera's axes): the one number the boards leave least decided, as the scene gives it with its
rotation's share of its variance. It is joined to the graph at its linearisation (``solvers.scene_term``: the
joint covariance of every sensor's pose, and the posterior's samples, moved with it). Not the scene's whole
estimate: on simulated offices its rotation was 0.3-1.5 degrees off with a covariance that admitted a fifth of
that (before each contour was measured along its ring), and joined in full it moved the boards' estimate away
from the truth (docs/bench/scene_joint.md).

Two tests, each Hotelling's F on the scene's blocks at ``ALPHA``: along the weak direction (the term's own) and
over every direction the scene constrains. Where either fails, the scene and the boards disagree, and one of
them is off: not joined, and the verdict says CHECK (whichever is off: a board calibration 10 cm off along the
weak direction leads the scene to a minimum of its own between the two, which then disagrees with the boards
over every direction more than along the weak one). Before each contour was measured along its ring, the scene's
estimate was turned 0.3-1.5 degrees on simulated offices with the board left out and an every-direction
disagreement was put down to the scene (not believed, the boards' verdict unchanged); it no longer is.
Where the scene's cost holds another minimum as low beyond its covariance (undecided), the term is not joined
and the boards' verdict stands. Where not joined, the boards' estimate stands and the record keeps the boards',
the scene's and the would-be joint estimates.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from geometry.rotations import T_inverse, T_log, T_retract

from ..errors import LidarcamError
from ..io.rig_dataset import is_rig
from ..solvers.rig_graph import pair_transform
from ..solvers.scene_term import JoinedTerm, join_pair_measurement, join_pair_translation
from .result import COVARIANCE_CONVENTION
from .scene_check import ALPHA, SceneCheck, check_scene
from .verdict import CHECK


@dataclass(frozen=True, eq=False)
class SceneWitness:
    """The scene's term for one camera-LiDAR pair (``calibrate --scene``; ``result.scene[(camera, lidar)]``).

    Attributes
    ----------
    camera, lidar : str
        The pair's sensors.
    T_boards, C_boards : numpy.ndarray
        The boards' estimate (4x4 ``T_camera_lidar``) and its 6x6 covariance, before the scene's term.
    check : SceneCheck or None
        The scene's check from the boards' estimate (the scene's estimate and covariance); None where it could
        not be made (``problem`` says why).
    term, overall : JoinedTerm or None
        The term along the boards' weak direction (joined, when joined) and the test over every direction the
        scene constrains (``d2``, ``dof``, ``p_value``).
    T_joint, C_joint : numpy.ndarray or None
        The joint estimate and covariance: the result's when joined, what joining would have given otherwise.
    joined : bool
        Whether the result's estimate is the joint one.
    reason : str or None
        Why not joined.
    problem : str or None
        Why the scene's check could not be made.
    contradicts : bool
        Whether the scene and the boards disagree, along the weak direction or over every direction the scene
        constrains (the verdict's CHECK).
    """

    camera: str
    lidar: str
    T_boards: np.ndarray
    C_boards: np.ndarray
    check: SceneCheck | None = None
    term: JoinedTerm | None = None
    overall: JoinedTerm | None = None
    T_joint: np.ndarray | None = None
    C_joint: np.ndarray | None = None
    joined: bool = False
    reason: str | None = None
    problem: str | None = None
    contradicts: bool = False

    @property
    def C_scene(self) -> np.ndarray | None:
        """The scene's covariance as joined: the check's as it believes it (``SceneCheck.believed_covariance``)."""
        return None if self.check is None else self.check.believed_covariance

    def weak_direction(self) -> np.ndarray:
        """The boards' least certain translation direction, a unit vector in the camera's frame."""
        R = self.T_boards[:3, :3]
        _, V = np.linalg.eigh(self.C_boards[3:, 3:])
        u = R @ V[:, -1]
        return u * np.sign(u[np.argmax(np.abs(u))])

    def along_weak(self) -> list[tuple[str, float, float]]:
        """``(which, mm, sd mm)`` along :meth:`weak_direction` for the boards', the scene's and the joint
        estimates (those there are)."""
        u = self.weak_direction()
        rows = [("boards", self.T_boards, self.C_boards)]
        if self.check is not None:
            rows.append(("scene", self.check.fit.T_camera_lidar, self.C_scene))
        if self.T_joint is not None:
            rows.append(("joint", self.T_joint, self.C_joint))
        out = []
        for which, T, C in rows:
            R = T[:3, :3]
            out.append((which, 1000 * float(u @ T[:3, 3]), 1000 * float(np.sqrt(max(u @ R @ C[3:, 3:] @ R.T @ u, 0)))))
        return out

    def concerns(self, prefix: str) -> list[tuple[str, str]]:
        """The verdict's concerns: CHECK where the scene and the boards disagree; none otherwise (a term not joined
        for another reason leaves the boards' estimate and its own verdict)."""
        return [(CHECK, f"{prefix}{self.reason}")] if self.contradicts else []

    def to_dict(self) -> dict:
        out = {"joined": self.joined, "reason": self.reason, "problem": self.problem,
               "T_camera_lidar_boards": self.T_boards.tolist(), "covariance_boards": self.C_boards.tolist(),
               "covariance_convention": COVARIANCE_CONVENTION,
               "covariance_excess": None if self.check is None else self.check.excess,
               "weak_direction_camera": self.weak_direction().tolist(),
               "along_weak_direction_mm": [{"estimate": w, "mm": v, "sd_mm": s} for w, v, s in self.along_weak()]}
        if self.check is not None:
            out["scene"] = {"T_camera_lidar": self.check.fit.T_camera_lidar.tolist(),
                            "covariance": self.C_scene.tolist(), "check_p_value": self.check.test["p_value"],
                            "frames_used": list(self.check.frames_used), "skipped": self.check.skipped,
                            "contour_returns": self.check.fit.points, "rms_px": self.check.fit.rms_px,
                            "rival_minima": len(self.check.rivals)}
        for key, t in (("along_weak_direction", self.term), ("every_direction", self.overall)):
            if t is not None:
                out.setdefault("boards_against_scene", {})[key] = {
                    "d2": t.d2, "dof": t.dof, "p_value": t.p_value, "alpha": ALPHA,
                    "statistic": "Hotelling's F on the scene's blocks"}
        if self.T_joint is not None:
            out["joint"] = {"T_camera_lidar": self.T_joint.tolist(), "covariance": self.C_joint.tolist()}
        return out


def _moved(T_ref: dict, names: tuple, dx: np.ndarray) -> dict:
    return {n: T_retract(T_ref[n], dx[6 * k:6 * k + 6]) for k, n in enumerate(names)}


def with_scene(result, rng: np.random.Generator, camera: str = "cam0", lidar: str = "lidar0"):
    """A board calibration with the scene's term joined where the scene agrees (``calibrate --scene``).

    The scene's estimate is sought near the boards' (the board left out), tested against it, and its translation
    along the boards' weak direction joined to the graph's estimate, covariance and posterior samples where the
    two agree (module docstring).

    Parameters
    ----------
    result : RigResult
        A pair or rig folder's calibration (``estimators.calibrate``), ``lidar`` a 3D LiDAR whose sweeps give each
        return's beam.
    rng : numpy.random.Generator
        Draws the scene's noise that moves the posterior's samples.
    camera, lidar : str
        The pair's sensors (a pair folder's ``cam0`` and ``lidar0``; a rig folder's camera and 3D LiDAR: called
        once per pair, each joined on the estimate the ones before it left).

    Returns
    -------
    RigResult
        ``result`` with the joint estimate where joined (else unchanged), and ``result.scene[(camera, lidar)]``: the
        :class:`SceneWitness` (the boards', the scene's and the joint estimates, the tests, why not joined). Its
        verdict says CHECK where the scene and the boards disagree along the weak direction.
    """
    pair = result.pair(camera, lidar)
    witness = SceneWitness(camera, lidar, pair.T, pair.covariance)
    sol, post = result.solution, result.posterior
    others = dict(result.scene or {})  # the rig's other pairs' terms, joined before this one

    def ended(w: SceneWitness, **changes):
        return replace(result, **changes, scene={**others, (camera, lidar): w})

    try:
        check = check_scene(result.rig.root, pair.T, camera=result.camera_model(camera),
                            sensors=(camera, lidar) if is_rig(result.rig.root) else None)
    except LidarcamError as exc:
        return ended(replace(witness, problem=exc.problem))
    witness = replace(witness, check=check)
    u = witness.weak_direction()
    P = sol.covariance_joint if post is None else post.covariance_joint
    T_ref = sol.T_ref if post is None else post.T_ref
    T_s, C_s, n = check.fit.T_camera_lidar, witness.C_scene, check.fit.blocks
    overall = join_pair_measurement(sol.names, T_ref, P, camera, lidar, T_s, C_s, blocks=n)
    term = join_pair_translation(sol.names, T_ref, P, camera, lidar, T_s, C_s, u, blocks=n)
    joint = _moved(T_ref, sol.names, term.dx)
    ix = np.r_[6 * sol.names.index(camera):6 * sol.names.index(camera) + 6,
               6 * sol.names.index(lidar):6 * sol.names.index(lidar) + 6]
    T_joint, C_joint = pair_transform(joint[camera], joint[lidar], term.covariance[np.ix_(ix, ix)])
    witness = replace(witness, term=term, overall=overall, T_joint=T_joint, C_joint=C_joint)
    (_, boards_mm, _), (_, scene_mm, _) = witness.along_weak()[:2]
    angle = float(np.degrees(np.linalg.norm(T_log(T_inverse(pair.T) @ T_s)[:3])))
    where = f"{scene_mm - boards_mm:+.1f} mm from the boards' along their weak direction"
    if overall is None:
        return ended(replace(witness, reason="the scene constrains no direction: not joined"))
    if term.p_value < ALPHA or overall.p_value < ALPHA:
        along = term.p_value < ALPHA
        test = (f"p = {term.p_value:.2g} along it" if along else
                f"p = {term.p_value:.2g} along it, {overall.p_value:.2g} over its {overall.dof} directions")
        reason = (f"the scene puts the LiDAR {where} ({test}; turned {angle:.2f} deg from them): not joined, the "
                  "boards' estimate stands; one of the two is off (how often the scene alone does so with the boards "
                  "right, on simulated scenes: docs/bench/scene_joint.md); look at scene_check.html, at the "
                  "boards' outlines in the report, and at the intrinsics (a camera's error away from the boards "
                  "moves the scene's estimate, not the boards')")
        return ended(replace(witness, reason=reason, contradicts=True))
    if check.rivals:
        reason = ("the scene's cost holds other minima as low beyond its covariance: its estimate is undecided, "
                  "not joined")
        return ended(replace(witness, reason=reason))
    # Joined: the solution's poses and covariance (its own Laplace one moved by its own gain) and the posterior's.
    own = term if post is None else join_pair_translation(sol.names, sol.T_ref, sol.covariance_joint, camera, lidar,
                                                           T_s, C_s, u, blocks=n)
    solution = replace(sol, T_ref=_moved(sol.T_ref, sol.names, own.dx), covariance_joint=own.covariance)
    posterior = None if post is None else replace(post, T_ref=joint, xi=term.moved_samples(post.xi, rng), _pairs={},
                                                  _sensor_T={})
    return ended(replace(witness, joined=True), solution=solution, posterior=posterior)
