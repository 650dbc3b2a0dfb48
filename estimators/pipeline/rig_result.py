"""A rig's result: the record (``RigResult``), the words for a LiDAR's range terms, and the rig's
calibration.json.
"""
from __future__ import annotations

import copy
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .. import __version__
from ..io.measurement_store import rig_as_pair
from ..io.output import write_json_atomic, write_npz_atomic
from ..io.rig_dataset import RigDataset
from ..solvers.closed_form import describe_direction
from ..solvers.edges_in_graph import conflict_words
from ..solvers.intrinsics_refinement import param_names
from ..solvers.posterior import INTERVAL_LEVELS
from ..solvers.range_model import OFFSET_HELD_P
from ..solvers.rig_graph import RigSolution
from ..solvers.rig_posterior import RigPosterior
from .pair_estimate import PairEstimate
from .result import CONVENTION, COVARIANCE_CONVENTION, frame_dict
from .rig_measurement import MIN_PAIR_FRAMES
from .verdict import plane_residuals, returns_without_terms
from .verdict import Verdict, rig_verdict

# A sensor's noise is scaled by its chi-square per degree of freedom whenever that is above 1
# (``rig_graph.solve_rig``); the warning that its factors disagree beyond their noise is given when its chi-square
# is beyond this tail probability.
NOISE_WARNING_P = 0.01


@dataclass(frozen=True, eq=False)
class RigResult:
    """A rig's calibration (``calibrate_rig``): every sensor's pose from one graph; ``pair(a, b)`` gives any two.

    Attributes
    ----------
    rig : RigDataset
        The rig folder calibrated.
    solution : RigSolution
        The joint graph's estimate: every sensor's pose in the reference's frame, the joint covariance, the noise
        scales (``solvers.rig_graph``).
    cameras : dict
        Each camera's intrinsics (``CameraModel``) used.
    pairwise : dict
        The camera-LiDAR pairs solved alone: ``(camera, lidar) -> (T, covariance, frames)``.
    frames_used, skipped : dict
        Per sensor, the frames it contributed, and those skipped with their reasons (``stem -> reason``).
    warnings : tuple of str
        Everything that limits trust in the result, most important first.
    timings_s : dict
        Stage times (s).
    """

    rig: RigDataset
    solution: RigSolution
    cameras: dict
    pairwise: dict
    frames_used: dict
    skipped: dict
    warnings: tuple[str, ...]
    timings_s: dict
    # Each camera-LiDAR pair's measured frames (``(camera, lidar) -> [FrameMeasurement]``), for the report.
    pair_frames: dict | None = None
    # The frames each pair of sensors shares where both found the board (``(a, b) -> count``; a camera-LiDAR
    # pair's usable frames, a camera pair's frames both saw).
    links: dict | None = None
    # The rig's posterior (``solvers.rig_posterior``) when sampled, and the views the graph was solved from.
    posterior: RigPosterior | None = None
    camera_views: tuple = ()
    lidar_views: tuple = ()
    # The board pose that most helps the weakest camera-LiDAR pair (``analysis.rig_layout``), with that pair's
    # predicted standard deviations before and after it; None when none was computed or none is feasible.
    next_pose: dict | None = None
    # Each LiDAR's range model: ``model`` (``none``, ``offset``, ``per-ring``, ``offset+dark`` or ``full``),
    # ``prior_sd_m``, ``chosen_by`` (the camera-LiDAR pair whose refinement chose it), its ``reason`` and ``tests``
    # under ``auto``, and with terms each one's estimate (``rig_terms.ranged_views``).
    range_models: dict = field(default_factory=dict)
    # Each 3D camera-LiDAR pair's board-edges check under the joint estimate (``(camera, lidar) -> record``, as a
    # single pair's ``board_edges``; :func:`pairs_outline_checks`).
    outline_checks: dict = field(default_factory=dict)
    # With ``--edges``: each LiDAR's board-edges record (:func:`with_edges`).
    edges: dict = field(default_factory=dict)
    # What every sensor measured (``io.measurement_store.RigMeasurements``): ``source`` says measured or cache.
    measurements: object = None
    # The camera-LiDAR pairs (a 2D scanner's, with few boards) whose own boards leave a second minimum with at
    # least ``AMBIGUOUS_MASS`` of the posterior mass: ``(camera, lidar) -> modes`` (``solution_selection.Mode``).
    # The joint graph starts from the most probable; its covariance is that one's, its posterior mixes them all.
    ambiguous_pairs: dict = field(default_factory=dict)
    # With the intrinsics refined: whether that lowers the rig's disagreement beyond chance
    # (``rig_graph.intrinsics_test``).
    intrinsics_test: dict | None = None
    # Without: each 3D camera-LiDAR pair's, whether its planes disagree in a way its camera's intrinsics explain
    # (``(camera, lidar) -> record``, a single pair's ``intrinsics_check``).
    intrinsics_checks: dict = field(default_factory=dict)
    # Each camera-LiDAR pair's own solve (``(camera, lidar) -> CalibrationResult``, ``rig_calibration.PairsAlone``).
    pair_results: dict = field(default_factory=dict)
    # A still-pose recording's clock offsets from its board's motion between the poses: each 3D LiDAR's against the
    # camera that followed the board (``lidar -> offset_between_poses.OffsetBetweenPoses``; a pair folder's
    # ``motion.npz``, a rig's ``lidar0/motion.npz``: ``rig_calibration._with_time_offset``).
    time_offsets: dict = field(default_factory=dict)
    # With ``calibrate --scene``: the scene's term for a pair folder's pair (``(camera, lidar) ->
    # scene_witness.SceneWitness``): the boards', the scene's and the joint estimates, and whether it was joined.
    scene: dict = field(default_factory=dict)

    @property
    def time_offset(self):
        """A pair folder's clock offset (``OffsetBetweenPoses``), None for a rig of more sensors or without one."""
        if len(self.rig.cameras) == 1 and len(self.rig.lidars) == 1:
            return self.time_offsets.get(self.rig.lidars[0].name)
        return None

    def pair(self, a: str, b: str) -> PairEstimate:
        """Sensors ``a`` and ``b``'s :class:`PairEstimate` from the joint solution (``result.pair("cam0",
        "lidar0").T_camera_lidar``)."""
        names = self.solution.names
        for n in (a, b):
            if n not in names:
                raise KeyError(f"{n!r} is not a sensor of this rig's solution ({', '.join(names)})")
        T, C = self.solution.transform(a, b)
        samples, modes = None, {}
        if self.posterior is not None:
            samples = self.posterior.pair_samples(a, b)
            C = np.cov(samples, rowvar=False)
            if self.posterior.mode_T_ref:
                modes = dict(mode_index=self.posterior.mode_index, mode_centers=self.posterior.mode_centers(a, b),
                             mode_weights=self.posterior.mode_weights)
        links = self.links or {}
        return PairEstimate(a, b, T, C, samples, int(links.get((a, b), links.get((b, a), 0))), **modes)

    def only_pair(self) -> PairEstimate:
        """A two-sensor rig's (a pair folder's) one camera-LiDAR pair; AttributeError for a larger rig, whose pairs
        :meth:`pair` gives by name."""
        if len(self.rig.cameras) != 1 or len(self.rig.lidars) != 1:
            raise AttributeError(f"a rig of {len(self.rig.cameras)} camera(s) and {len(self.rig.lidars)} LiDAR(s) has "
                                 "no single T_camera_lidar: use result.pair(camera, lidar)")
        return self.pair(self.rig.cameras[0].name, self.rig.lidars[0].name)

    # A pair folder's estimate as the pair's own record gave it (``result.pair("cam0", "lidar0")``'s).
    T_camera_lidar = property(lambda self: self.only_pair().T, doc="4x4, a pair folder's ``T_camera_lidar``.")
    covariance = property(lambda self: self.only_pair().covariance,
                          doc="6x6, its covariance: the posterior samples' when sampled, else the graph's.")
    samples = property(lambda self: self.only_pair().samples, doc="M x 6 tangent samples of it, or None.")
    std_rotation_deg = property(lambda self: self.only_pair().std_rotation_deg, doc="About the LiDAR's axes.")
    std_translation_mm = property(lambda self: self.only_pair().std_translation_mm, doc="Along the LiDAR's axes.")

    @property
    def frames(self) -> list:
        """A pair folder's frames as measured, in name order (each ``FrameMeasurement``: the board in the image and in
        the scan, or why not), as its measurements.npz holds them (``io.measurement_store.rig_as_pair``)."""
        self.only_pair()
        return list(rig_as_pair(self.measurements, self.rig.board, self.rig.lidars[0].lidar).frames)

    def report(self, out_dir: str | Path) -> Path:
        """Write ``out_dir/report.html`` and its figures (``analysis.rig_report.write_rig_report``); a result solved
        from measurements in memory, without its folder's images, has none to draw on and is refused."""
        from ..analysis.rig_report import write_rig_report
        from ..errors import DatasetError

        if not any(Path(p).is_file() for c in self.rig.cameras for _, p in c.files):
            raise DatasetError("no image of this rig's frames is on disk to draw the report on (a result solved from "
                               "measurements in memory)", path=self.rig.root,
                               hint="calibrate the dataset folder (or lidarcam calibrate DATASET) for its report")
        return write_rig_report(self, out_dir)

    def camera_model(self, name: str):
        """Camera ``name``'s model as the solution has it: its refined intrinsics where they were refined, else the
        ones given (``cameras``)."""
        return self.solution.camera_model(name, self.cameras[name])

    @property
    def ambiguous(self) -> bool:
        """A camera-LiDAR pair's boards leave two answers (:attr:`ambiguous_pairs`): the printout starts with it
        and ``--strict`` exits non-zero."""
        return bool(self.ambiguous_pairs)

    @property
    def contradicted(self) -> str | None:
        """As a single pair's result: how a LiDAR's planes and edges conflict beyond their noise, each named
        (``edges_in_graph.conflict_words``; the joint covariance then holds both answers), or None."""
        said = [f"{name}: {w}" for name, r in self.edges.items() if (w := conflict_words(r)) is not None]
        return "; ".join(said) or None

    @property
    def verdict(self) -> Verdict:
        """``OK``, ``CHECK: ...`` or ``UNTRUSTED: ...`` (``pipeline.verdict``), by the rules a single pair's takes,
        each reason naming its sensor or pair."""
        return rig_verdict(self)

    def layout(self) -> dict:
        """Where the rig is weakest: each camera-LiDAR pair's largest translation standard deviation (mm, the
        joint graph's) and the direction (camera axes) and advice for it (``closed_form.describe_direction``),
        the weakest pair, and the sensor pairs that share some frames but fewer than ``MIN_PAIR_FRAMES`` (a
        camera-LiDAR pair is then not solved alone, but for a scanner solved from two boards' segment ends; two
        cameras rest on one or two boards)."""
        pairs = {f"T_{c.name}_{lid.name}": PairEstimate(c.name, lid.name, *self.solution.transform(c.name, lid.name),
                                                        None, 0).weakest_translation()
                 for c in self.rig.cameras for lid in self.rig.lidars}
        weakest = max(pairs, key=lambda k: pairs[k]["max_translation_sd_mm"]) if pairs else None
        few = {f"{a}-{b}": n for (a, b), n in (self.links or {}).items() if 0 < n < MIN_PAIR_FRAMES}
        return {"pairs": pairs, "weakest_pair": weakest, "links_with_few_frames": few, "next_pose": self.next_pose}

    def pairs(self) -> list[tuple[str, str]]:
        """Every camera-LiDAR pair, every camera-camera and every LiDAR-LiDAR pair (earlier sensor first), in
        sensor order."""
        cams, lidars = [s.name for s in self.rig.cameras], [s.name for s in self.rig.lidars]
        out = [(c, lid) for c in cams for lid in lidars]
        out += [(a, b) for i, a in enumerate(cams) for b in cams[i + 1:]]
        out += [(a, b) for i, a in enumerate(lidars) for b in lidars[i + 1:]]
        return out

    def noise(self, name: str) -> dict:
        """The noise levels a sensor was weighed with, at its noise scale (what ``lidarcam validate`` scores held-out
        frames against): a camera's corner noise (px); a LiDAR's range noise, its boards' median plane error
        (m) and their scatter along the range terms' weak direction (m)."""
        scale = float(np.sqrt(self.solution.noise_scale.get(name, 1.0)))
        for c in self.camera_views:
            if c.name == name:
                return {"corner_noise_px": float(c.sigma_px) * scale}
        for lv in self.lidar_views:
            if lv.name == name:
                floors = [pe.floor_m for pe in (lv.plane_error or {}).values() if pe is not None]
                return {"range_noise_m": float(lv.sigma_m) * scale,
                        "plane_floor_m": float(np.median(floors)) if floors else 0.0,
                        "board_scatter_m": float(lv.tau_m)}
        return {}

    def returns_without_terms(self, camera: str, lidar: str, frames: list) -> dict:
        """Per frame of a camera-LiDAR pair, its board's returns with the LiDAR's range terms taken off, at the joint
        graph's values (``verdict.returns_without_terms``): what its plane residuals are drawn from. Empty where the
        joint graph holds no terms for the LiDAR."""
        joint = {n: t["value_m"] for n, t in (self.range_models.get(lidar, {}).get("terms") or {}).items()}
        own = (self.pair_results or {}).get((camera, lidar))
        if not joint or own is None or own.refinement is None:
            return {}
        return returns_without_terms(frames, own.refinement.range_model, joint, self.rig.board,
                                     self.solution.transform(camera, lidar)[0])

    def pair_keys(self, camera: str, lidar: str) -> dict:
        """The keys a single pair's calibration.json gives (``CalibrationResult.to_dict``), for the camera-LiDAR
        pair ``(camera, lidar)``: its transform, covariance and posterior intervals from the joint graph; its
        noise, board edges, intrinsics and their check, as the rig weighed and checked them; and from the pair's own
        solve (:attr:`pair_results`), its frames (each with its fit and its planes' residual under the joint
        estimate), its start, consistency, range model's choice, normals' spread and a scanner's minimal
        solutions. A two-sensor rig's file carries them at its top level (docs/reference/calibration_json.md)."""
        est = self.pair(camera, lidar)
        own = self.pair_results.get((camera, lidar))
        ref = own.refinement if own is not None else None
        out = {"tool": "lidarcam", "convention": CONVENTION, **est.camera_lidar_keys(),
               "init": own.init if own is not None else "closed-form", "refine": "factor-graph",
               "covariance_convention": COVARIANCE_CONVENTION}
        if est.samples is not None:
            out["covariance_laplace"] = self.solution.transform(camera, lidar)[1].tolist()
            out["intervals"] = {f"{round(100 * level)}%": {
                "rotation_deg_about_lidar_xyz": np.degrees(est.intervals(level)[:3]).tolist(),
                "translation_mm_along_lidar_xyz": (1000 * est.intervals(level)[3:]).tolist()}
                for level in INTERVAL_LEVELS}
            out["credible_regions"] = est.regions()
        else:
            out["covariance_note"] = "Laplace approximation (no posterior samples were drawn)"
        lid_noise = self.noise(lidar)
        out["noise"] = {"corner_noise_px": self.noise(camera).get("corner_noise_px"),
                        "corner_residual_px": ref.corner_residual_px if ref is not None else None,
                        "range_noise_m": lid_noise.get("range_noise_m"),
                        "plane_floor_m": lid_noise.get("plane_floor_m")}
        if ref is not None:
            out["consistency"] = {"variance_factor": ref.variance_factor, "dof": ref.consistency_dof,
                                  "p_value": ref.consistency_p}
        out["iterations"] = self.solution.iterations
        fit = ref.range_model if ref is not None else None
        out["lidar_range_model"] = fit.to_dict() if fit is not None else {
            "requested": "none", "chosen": "none", "reason": "not requested", "terms": []}
        joint = self.range_models.get(lidar, {}).get("terms") or {}
        for term in out["lidar_range_model"]["terms"]:  # each term as the joint graph estimates it
            if term["term"] in joint:
                term.update(value_mm=1000 * joint[term["term"]]["value_m"], std_mm=1000 * joint[term["term"]]["sd_m"])
        edges = self.edges.get(lidar) or self.outline_checks.get((camera, lidar))
        out["board_edges"] = edges if edges is not None else {"used": False}
        out["contradicted"] = conflict_words(self.edges.get(lidar) or {})
        measured = getattr(self.measurements, "pairs", {}).get((camera, lidar)) or (self.pair_frames or {}).get(
            (camera, lidar), [])
        used = set(self.frames_used.get(lidar, ())) & set(self.frames_used.get(camera, ()))
        usable = [f for f in measured if f.usable]
        residuals = plane_residuals(est.T, usable, self.returns_without_terms(camera, lidar, usable))
        fits = {f.name: f for f in ref.frames} if ref is not None else {}
        frames = []
        for f in measured:
            d = frame_dict(f, residuals.get(f.name), fits.get(f.name))
            if f.usable and f.name not in used:  # the rig left it out: its reason is the rig's
                d.update(used=False, reason=self.skipped.get(lidar, {}).get(f.name) or d["reason"])
            frames.append(d)
        out.update(frames_used=sum(d["used"] for d in frames), frames_total=len(frames), frames=frames)
        if own is not None:
            axis, advice = describe_direction(own.weakest_direction_camera)
            out["layout"] = {"normal_singular_values": own.normal_singular_values.tolist(),
                             "condition_number": own.condition_number,
                             "weakest_direction_camera": own.weakest_direction_camera.tolist(),
                             "weakest_direction_words": f"{axis}: to constrain it further, {advice}"}
            out.update(own.minimal_dict())
        out["intrinsics"] = self.camera_model(camera).as_dict()
        if camera in (self.solution.intrinsics or {}):
            out["intrinsics_refinement"] = self._intrinsics_record(camera)
        out["intrinsics_check"] = self.intrinsics_checks.get((camera, lidar))
        return out

    def _intrinsics_record(self, camera: str) -> dict:
        """A pair's file's ``intrinsics_refinement``: each of the camera's intrinsics given and refined with the
        rig, its standard deviation, how far it moved in those and its prior's (dataset.yaml's ``param_std``), and
        the rig's test whether refining them lowered its factors' disagreement (``intrinsics_test``)."""
        params, sd = self.solution.intrinsics[camera]
        given = self.cameras[camera]
        prior = given.param_std
        test = self.intrinsics_test or {}
        return {"parameters": [{"name": n, "given": float(g), "refined": float(v), "std": float(e),
                                "shift_in_std": float((v - g) / e) if e > 0 else None,
                                "prior_sd": None if prior is None else float(prior[k])}
                               for k, (n, g, v, e) in enumerate(zip(param_names(len(params)), given.params, params,
                                                                    sd))],
                "prior": "given camera.param_std" if prior is not None else
                         "none: estimated from the frames' corners and planes",
                **{k: test.get(k) for k in ("chi_square_given", "chi_square_refined", "dof", "p_value")},
                "lowers_overdispersion": test.get("lowers_disagreement"),
                "lowers_overdispersion_p": test.get("p_value")}

    def to_json(self) -> dict:
        sol, ref = self.solution, self.rig.reference

        def entry(T, cov) -> dict:  # a pair's spread as PairEstimate gives it
            return PairEstimate("", "", T, cov, None, 0).transform_keys()

        sensors = []
        for s in self.rig.sensors:
            e = entry(sol.T_ref[s.name], sol.covariance(s.name))
            sensors.append({"name": s.name, "type": s.type, f"T_{ref}_{s.name}": e.pop("T"), **e,
                            "frames_used": len(self.frames_used.get(s.name, ())),
                            "noise_scale": sol.noise_scale.get(s.name, 1.0)})
            noise = self.noise(s.name)
            if noise:
                sensors[-1]["noise"] = noise
            if s.name in self.edges:
                sensors[-1]["board_edges"] = self.edges[s.name]
            if s.name in self.range_models:
                record = sensors[-1]["range_model"] = copy.deepcopy(self.range_models[s.name])
                if self.posterior is not None and s.name in self.posterior.range_terms:
                    q = np.percentile(self.posterior.range_terms[s.name], [2.5, 97.5], axis=0)
                    record["posterior_95%_m"] = q[:, 0].tolist()
                    for k, term in enumerate(record["terms"].values()):
                        term["posterior_95%_m"] = q[:, k].tolist()
        transforms = {f"T_{a}_{b}": entry(*sol.transform(a, b)) for a, b in self.pairs()}
        for (a, b), record in self.outline_checks.items():
            transforms[f"T_{a}_{b}"]["board_edges"] = record
        for (a, b), record in self.intrinsics_checks.items():
            transforms[f"T_{a}_{b}"]["intrinsics_check"] = record
        posterior = None
        if self.posterior is not None:
            for a, b in self.pairs():
                transforms[f"T_{a}_{b}"]["posterior"] = self.pair(a, b).summary()
            posterior = {**self.posterior.diagnostics(), "covariance_joint": self.posterior.covariance_joint.tolist(),
                         "file": "posterior.npz"}
        pairwise = {f"T_{c}_{lid}": {**entry(T, cov), "frames": n} for (c, lid), (T, cov, n) in self.pairwise.items()}
        cameras = {n: {"model": m.model, "width": m.width, "height": m.height, "K": m.K.tolist(),
                       "dist": m.dist.tolist(), "source": m.source} for n, m in self.cameras.items()}
        for n, (p, sd) in (sol.intrinsics or {}).items():
            refined = self.cameras[n].with_params(p)
            cameras[n].update({"given_params": self.cameras[n].params.tolist(), "refined_params": p.tolist(),
                               "refined_params_sd": sd.tolist(), "K": refined.K.tolist(),
                               "dist": refined.dist.tolist(), "source": "refined with the rig"})
        pair = {}
        if len(self.rig.cameras) == 1 and len(self.rig.lidars) == 1:  # a pair's rig: the pair's keys too
            pair = self.pair_keys(self.rig.cameras[0].name, self.rig.lidars[0].name)
            if self.time_offset is not None:
                pair.update(self.time_offset.to_dict())
        elif self.time_offsets:
            from .offset_between_poses import time_offsets_keys  # here: it loads the moving board's solvers

            pair.update(time_offsets_keys(self.time_offsets))
        if self.scene:
            pair["scene"] = {f"T_{c}_{lid}": w.to_dict() for (c, lid), w in self.scene.items()}
        ambiguous = {f"T_{c}_{lid}": [{"T_camera_lidar": m.T_camera_lidar.tolist(), "posterior_mass": m.mass,
                                       "covariance": m.refinement.covariance.tolist()} for m in modes]
                     for (c, lid), modes in self.ambiguous_pairs.items()}
        for s in sensors:
            s["frames"] = list(self.frames_used.get(s["name"], ()))
        return {"verdict": self.verdict.to_dict(), "rig": True, **pair, "dataset": str(self.rig.root), "reference": ref,
                "ambiguous_pairs": ambiguous,
                "sensors": sensors,
                "transforms": transforms,
                "layout": {**self.layout(), **pair.get("layout", {})},
                "covariance_joint": sol.covariance_joint.tolist(), "posterior": posterior,
                "pairwise_only": pairwise, "cameras": cameras, "intrinsics_test": self.intrinsics_test,
                # a two-sensor rig's: the pair's count (each sensor's frames are in ``sensors``)
                "frames_used": pair.get("frames_used", {n: list(v) for n, v in self.frames_used.items()}),
                "skipped": self.skipped, "warnings": list(self.warnings), "timings_s": self.timings_s,
                "measurements_source": getattr(self.measurements, "source", None), "version": __version__,
                "convention": "T_a_b maps points from b's frame into a's: p_a = R p_b + t. Covariances are 6x6 in "
                              "GTSAM's Pose3 right tangent, T_true = T_hat * Exp(xi), xi = [rot; trans]; "
                              "covariance_joint holds every sensor's T_<reference>_<sensor> in the order of "
                              "sensors (the reference's block is zero)."}


def range_model_words(record: dict) -> str:
    """A LiDAR's range model in words (its record: ``rig_terms.ranged_views``, the pair's tests)."""
    tests = list(record.get("tests", ()))
    said = ", ".join(f"{t['model']}{' with the ring ends' if t.get('with_ring_ends') else ''} p = {t['p_value']:.2g}"
                     for t in tests)
    how = f"{record.get('chosen_by', 'its pair')}'s tests at {record['test_p']:g}: {said}" if tests else "requested"
    terms = record.get("terms") or {}
    if not terms:
        weak = record.get("weak_offset")
        held = (f"; an offset of {weak['offset_mm']:+.1f} mm (p = {weak['p_value']:.2g} < {OFFSET_HELD_P}) held in the "
                "covariance" if weak else "")
        return f"no range terms ({how}{held})" if tests else "no range terms (--range-model none)"
    parts = [f"range offset {1000 * terms['offset']['value_m']:+.1f} +- {1000 * terms['offset']['sd_m']:.1f} mm"]
    rings = [v["value_m"] for n, v in terms.items() if n.startswith("ring ")]
    if rings:
        parts.append(f"{len(rings)} ring offsets, spread (sd) {1000 * float(np.std(rings)):.1f} mm")
    if "dark" in terms:
        parts.append(f"black squares {1000 * terms['dark']['value_m']:+.1f} +- {1000 * terms['dark']['sd_m']:.1f} mm")
    parts += [f"{h['term']} held at 0 (estimated {h['estimate_mm']:+.0f} mm, beyond 3 prior sds)"
              for h in record.get("held_at_prior", ())]
    return "; ".join(parts) + f" ({how}; prior sd {1000 * record['prior_sd_m']:.0f} mm)"


def write_rig_calibration(result: RigResult, out: str | Path) -> Path:
    """Write a rig's ``calibration.json`` atomically.

    Parameters
    ----------
    result : RigResult
        From :func:`calibrate_rig`.
    out : str or Path
        The output folder (created when absent).

    Returns
    -------
    Path
        The file written (docs/reference/calibration_json.md, rigs); with a posterior, ``posterior.npz`` beside it
        first (``xi``: the samples of every sensor's pose, ``names``, ``T_ref``: the MAP poses in that order; a rig
        of one camera and one LiDAR writes a single pair's keys, ``xi`` its camera-LiDAR transform's samples,
        ``T_map`` its estimate and ``chain``, with several minima ``mode_index`` and ``mode_centers_xi``, the joint
        samples as ``xi_joint``).
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    post = result.posterior
    if post is not None:
        arrays = {"xi": post.xi, "names": np.array(post.names), "T_ref": np.array([post.T_ref[n] for n in post.names]),
                  "reference": np.array(post.reference), "noise_scale": post.camera_scale}
        if len(result.rig.cameras) == 1 and len(result.rig.lidars) == 1:
            pair = result.pair(result.rig.cameras[0].name, result.rig.lidars[0].name)
            arrays.update(xi_joint=post.xi, xi=pair.samples, T_map=pair.T, convention=np.array(COVARIANCE_CONVENTION),
                          chain=post.run.chain)
            if pair.mode_index is not None:
                arrays.update(mode_index=pair.mode_index, mode_centers_xi=pair.mode_centers)
        write_npz_atomic(out / "posterior.npz", arrays, compress=False)
    path = out / "calibration.json"
    write_json_atomic(path, result.to_json())
    return path


def write_calibration(result, out: str | Path) -> Path:
    """Write ``OUT/posterior.npz`` (when sampled) and then ``OUT/calibration.json``, each atomically.

    Parameters
    ----------
    result : RigResult or CalibrationResult
        The engine's (``estimators.calibrate``; :func:`write_rig_calibration`) or the pair's own solve's
        (``calibrate_pair``, ``solve``).
    out : str or Path
        The output folder (created when missing).

    Returns
    -------
    Path
        The path of ``calibration.json``.
    """
    if isinstance(result, RigResult):
        return write_rig_calibration(result, out)
    from .result import write_calibration as write_pair

    return write_pair(result, out)
