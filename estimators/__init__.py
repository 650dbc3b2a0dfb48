"""lidarcam: camera-LiDAR extrinsic calibration from planar boards, with honest uncertainty.

The Python API (the CLI is a thin shell over it). Frames and units: ``T_camera_lidar`` maps LiDAR points
into the camera frame, ``p_camera = R p_lidar + t``, metres and radians; covariances are 6x6 in GTSAM's
Pose3 tangent (``T_true = T_hat Exp(xi)``, ``xi = [rotation; translation]``, along the LiDAR's axes)::

    from estimators import simulate, load_dataset, calibrate
    path = simulate("/tmp/sim", n_poses=8, seed=1)           # or lidar="2d"
    result = calibrate(path, samples=2000)                   # the engine the command line runs: a RigResult
    result.verdict, result.T_camera_lidar, result.covariance, result.samples   # a pair folder's pair
    result.pair("cam0", "lidar0").intervals(0.95)            # any two sensors of a rig alike
    result.report("/tmp/sim-out")                            # report.html and its figures
    write_calibration(result, "/tmp/sim-out")                # calibration.json (+ posterior.npz)

Layout: ``analyse``, ``layout_from_plan``, ``layout_from_result``, ``suggest_poses``, ``cramer_rao_bound``.
Studies: ``parse_spec``, ``run_study`` (local processes or a Dask scheduler), ``run_coverage_study``.
Real rigs: ``extract_bag`` (a dataset folder from a ROS 1 / ROS 2 bag), ``export_calibration`` and
``write_export`` (ROS tf, URDF, KITTI, OpenCV YAML, JSON), ``load_calibration``.
Rigs of several sensors in one graph: ``load_rig``, ``calibrate_rig`` (``calibrate``'s engine, from a loaded rig),
``write_rig_calibration``, ``simulate_rig``, ``extract_rig_bag`` (a rig folder from a bag with several cameras and
LiDARs). A moving board's folder (``motion.npz``, from ``extract_bag``): ``calibrate_moving``, a rig's
``calibrate_moving_rig`` (the extrinsic and the clocks' offset, each LiDAR against the first camera).
The scene as a witness (no board needed): ``check_scene`` (a given extrinsic against the scene's contours and
edges), ``calibrate_targetless`` (the extrinsic refined from a guess on the scene alone), ``simulate_scene``
(a furnished room's frames with their truth).
``calibrate`` takes a pair folder as the rig of ``cam0`` and ``lidar0``; the pair's own solve, which starts each
camera-LiDAR pair of the engine, is ``calibrate_pair`` (or ``solve`` on measured frames: a ``CalibrationResult``).
Names are imported on first use, so that ``import estimators`` stays light.
"""

__version__ = "0.4.0"

_API = {
    "load_dataset": ("io.dataset", "load_dataset"),
    "Dataset": ("io.dataset", "Dataset"),
    "calibrate": ("rig_calibration", "calibrate"),
    "calibrate_pair": ("calibration", "calibrate_pair"),
    "solve": ("calibration", "solve"),
    "measure": ("pipeline.measurement", "measure"),
    "Measurements": ("io.measurement_store", "Measurements"),
    "save_measurements": ("io.measurement_store", "save_measurements"),
    "load_measurements": ("io.measurement_store", "load_measurements"),
    "write_calibration": ("pipeline.rig_result", "write_calibration"),
    "CalibrationResult": ("pipeline.result", "CalibrationResult"),
    "PairEstimate": ("pipeline.pair_estimate", "PairEstimate"),
    "RefinementOptions": ("solvers.refinement", "RefinementOptions"),
    "PosteriorOptions": ("solvers.posterior", "PosteriorOptions"),
    "simulate": ("simulation.simulator", "simulate_dataset"),
    "analyse": ("analysis.layout_analysis", "analyse"),
    "layout_from_plan": ("analysis.layout_analysis", "layout_from_plan"),
    "layout_from_result": ("analysis.layout_analysis", "layout_from_result"),
    "suggest_poses": ("analysis.layout_analysis", "suggest_poses"),
    "Layout": ("solvers.observation_model", "Layout"),
    "cramer_rao_bound": ("solvers.observation_model", "cramer_rao_bound"),
    "simulate_measurements": ("solvers.observation_model", "simulate_measurements"),
    "parse_spec": ("analysis.study", "parse_spec"),
    "run_study": ("analysis.study", "run_study"),
    "run_coverage_study": ("analysis.coverage_study", "run_study"),
    "extract_bag": ("io.bag_extract", "extract_bag"),
    "ExtractOptions": ("io.bag_extract", "ExtractOptions"),
    "export_calibration": ("io.export", "export_calibration"),
    "write_export": ("io.export", "write_export"),
    "load_calibration": ("io.export", "load_calibration"),
    "load_rig": ("io.rig_dataset", "load_rig"),
    "calibrate_rig": ("rig_calibration", "calibrate_rig"),
    "RigResult": ("pipeline.rig_result", "RigResult"),
    "write_rig_calibration": ("pipeline.rig_result", "write_rig_calibration"),
    "simulate_rig": ("simulation.rig_simulator", "simulate_rig"),
    "extract_rig_bag": ("io.rig_bag_extract", "extract_rig_bag"),
    "calibrate_moving": ("pipeline.moving_board", "calibrate_moving"),
    "calibrate_moving_rig": ("pipeline.moving_rig", "calibrate_moving_rig"),
    "check_scene": ("pipeline.scene_check", "check_scene"),
    "calibrate_targetless": ("pipeline.targetless", "calibrate_targetless"),
    "with_scene": ("pipeline.scene_witness", "with_scene"),
    "SceneWitness": ("pipeline.scene_witness", "SceneWitness"),
    "simulate_scene": ("simulation.furnished_room", "simulate_scene_dataset"),
}
__all__ = ["__version__", *_API]


def __getattr__(name: str):
    if name in _API:
        import importlib

        module, attr = _API[name]
        value = getattr(importlib.import_module(f".{module}", __name__), attr)
        globals()[name] = value
        return value
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
