"""graphopt's vertex and edge types, installed as ``graphopt.types``.

Every type is available at the package level (``from graphopt.types import EdgeSE2``); the
modules are imported on first use, so ``import graphopt.types`` stays as quick as
``import graphopt``.

=====================  ==========================================================================
module                 types
=====================  ==========================================================================
``vertices``           ``VertexSE3Expmap``, ``VertexPointXYZ``, ``VertexPointInverseDepth``
``bal``                ``VertexCameraBAL``, ``EdgeBALProjection``
``projection``         ``CameraParameters``, ``EdgeSE3ProjectXYZ``, ``EdgeProjectXYZ2UV``,
                       ``EdgeInverseDepthProjection``
``sba_pose``           ``StereoCameraParameters``, ``EdgeSE3ProjectXYZOnlyPose``,
                       ``EdgeStereoSE3ProjectXYZ``, ``EdgeStereoSE3ProjectXYZOnlyPose``,
                       ``EdgeSE3Expmap``
``sim3``               ``VertexSim3Expmap``, ``EdgeSim3``, ``EdgeSim3ProjectXYZ``,
                       ``EdgeInverseSim3ProjectXYZ`` (``sim3_lie``: g2o's Sim(3) exp/log,
                       ``sim3_matrix``)
``photometric``        ``PhotometricParams``, ``EdgePhotometricPatch``,
                       ``EdgePhotometricPatchInverseDepth``,
                       ``EdgePhotometricPatchInverseDepthHost``
``slam2d``             ``VertexSE2``, ``VertexPointXY``, ``EdgeSE2``, ``EdgeSE2PointXY``,
                       ``EdgeSE2Prior``
``slam3d``             ``VertexSE3``, ``ParameterSE3Offset``, ``EdgeSE3``, ``EdgeSE3PointXYZ``,
                       ``EdgeSE3Prior``
``slam3d_sensors``     ``EdgeSE3Offset``, ``EdgePointXYZ``, ``EdgeXYZPrior``, ``EdgeSE3XYZPrior``,
                       ``ParameterCamera``, ``EdgeSE3PointXYZDepth``,
                       ``EdgeSE3PointXYZDisparity``, ``EdgeSE3LotsOfXYZ`` (``.of(k)``)
``slam2d_sensors``     ``EdgePointXY``, ``EdgeXYPrior``, ``EdgeSE2XYPrior``,
                       ``EdgeSE2PointXYBearing``, ``ParameterSE2Offset``, ``EdgeSE2Offset``,
                       ``EdgeSE2PointXYOffset``, ``EdgeSE2PointXYCalib``,
                       ``EdgeSE2TwoPointsXY``, ``EdgeSE2LotsOfXY`` (``.of(k)``)
``sclam2d``            ``EdgeSE2SensorCalib``, ``VertexOdomDifferentialParams``,
                       ``EdgeSE2OdomDifferentialCalib``
``sba_cam``            ``VertexCam`` (g2o's ``SBACam``), ``EdgeProjectP2MC``,
                       ``EdgeProjectP2SC``, ``EdgeSBACam``, ``EdgeSBAScale``,
                       ``VertexIntrinsics``
``sba_expmap``         ``SBACameraParameters``, ``EdgeProjectXYZ2UVU``, ``EdgeProjectPSI2UV``
``icp``                ``EdgeVVGicp``, ``EdgeVVGicpPlaneToPlane``, ``VertexSCam``,
                       ``SCamParameters``, ``EdgeXyzVsc``
``slam_graph``         ``SlamGraph``, ``build_graph``, ``graph_file`` (g2o/TORO records ↔
                       optimizer), ``pose_graph_levenberg``, ``POSE_GRAPH_INITIAL_LAMBDA``
=====================  ==========================================================================
"""

from importlib import import_module as _import_module
from typing import Any as _Any

_WHERE = {
    "VertexSE3Expmap": "vertices", "VertexPointXYZ": "vertices",
    "VertexPointInverseDepth": "vertices",
    "VertexCameraBAL": "bal", "EdgeBALProjection": "bal",
    "CameraParameters": "projection", "EdgeSE3ProjectXYZ": "projection",
    "EdgeProjectXYZ2UV": "projection", "EdgeInverseDepthProjection": "projection",
    "StereoCameraParameters": "sba_pose", "EdgeSE3ProjectXYZOnlyPose": "sba_pose",
    "EdgeStereoSE3ProjectXYZ": "sba_pose", "EdgeStereoSE3ProjectXYZOnlyPose": "sba_pose",
    "EdgeSE3Expmap": "sba_pose",
    "VertexSim3Expmap": "sim3", "EdgeSim3": "sim3", "EdgeSim3ProjectXYZ": "sim3",
    "EdgeInverseSim3ProjectXYZ": "sim3", "sim3_matrix": "sim3_lie",
    "PhotometricParams": "photometric", "EdgePhotometricPatch": "photometric",
    "EdgePhotometricPatchInverseDepth": "photometric",
    "EdgePhotometricPatchInverseDepthHost": "photometric",
    "VertexSE2": "slam2d", "VertexPointXY": "slam2d", "EdgeSE2": "slam2d",
    "EdgeSE2PointXY": "slam2d", "EdgeSE2Prior": "slam2d",
    "VertexSE3": "slam3d", "ParameterSE3Offset": "slam3d", "EdgeSE3": "slam3d",
    "EdgeSE3PointXYZ": "slam3d", "EdgeSE3Prior": "slam3d",
    "EdgeSE3Offset": "slam3d_sensors", "EdgePointXYZ": "slam3d_sensors",
    "EdgeXYZPrior": "slam3d_sensors", "EdgeSE3XYZPrior": "slam3d_sensors",
    "ParameterCamera": "slam3d_sensors", "EdgeSE3PointXYZDepth": "slam3d_sensors",
    "EdgeSE3PointXYZDisparity": "slam3d_sensors", "EdgeSE3LotsOfXYZ": "slam3d_sensors",
    "EdgePointXY": "slam2d_sensors", "EdgeXYPrior": "slam2d_sensors",
    "EdgeSE2XYPrior": "slam2d_sensors", "EdgeSE2PointXYBearing": "slam2d_sensors",
    "ParameterSE2Offset": "slam2d_sensors", "EdgeSE2Offset": "slam2d_sensors",
    "EdgeSE2PointXYOffset": "slam2d_sensors", "EdgeSE2PointXYCalib": "slam2d_sensors",
    "EdgeSE2TwoPointsXY": "slam2d_sensors", "EdgeSE2LotsOfXY": "slam2d_sensors",
    "EdgeSE2SensorCalib": "sclam2d", "VertexOdomDifferentialParams": "sclam2d",
    "EdgeSE2OdomDifferentialCalib": "sclam2d",
    "VertexCam": "sba_cam", "EdgeProjectP2MC": "sba_cam", "EdgeProjectP2SC": "sba_cam",
    "EdgeSBACam": "sba_cam", "EdgeSBAScale": "sba_cam", "VertexIntrinsics": "sba_cam",
    "SBACameraParameters": "sba_expmap", "EdgeProjectXYZ2UVU": "sba_expmap",
    "EdgeProjectPSI2UV": "sba_expmap",
    "EdgeVVGicp": "icp", "EdgeVVGicpPlaneToPlane": "icp", "VertexSCam": "icp",
    "SCamParameters": "icp", "EdgeXyzVsc": "icp",
    "SlamGraph": "slam_graph", "build_graph": "slam_graph", "graph_file": "slam_graph",
    "pose_graph_levenberg": "slam_graph", "POSE_GRAPH_INITIAL_LAMBDA": "slam_graph",
}

__all__ = sorted(_WHERE)


def __getattr__(name: str) -> _Any:
    module = _WHERE.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(_import_module(f"{__name__}.{module}"), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return __all__
