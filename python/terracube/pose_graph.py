"""Pose-graph optimisation for loop closing (Ceres).

Nodes are rigid (4, 4) sensor-to-world poses; an edge holds the measured relative pose
``inv(pose[from_]) @ pose[to]`` and a 6x6 information matrix ordered (translation x y z,
rotation x y z). The residual of an edge is the translation difference of the estimated and
measured relative poses plus the rotation vector of their quaternion error, whitened by the
Cholesky factor of the information; edges marked ``robust`` (loop closures) go through a Huber
or Cauchy loss. The poses in ``fixed`` (the first by default) do not move.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field

import numpy as np

from . import _core

__all__ = ["PoseGraphEdge", "PoseGraphParams", "PoseGraphResult", "RobustLoss", "optimize_pose_graph"]

RobustLoss = _core.RobustLoss
PoseGraphResult = _core.PoseGraphResult


@dataclass
class PoseGraphEdge:
    """A measured relative pose, mirroring ``terracube::PoseGraphEdge``.

    Attributes
    ----------
    from_, to : int
        Node indices (``from`` is a Python keyword, hence the underscore).
    measurement : (4, 4) array
        The measured ``inv(pose[from_]) @ pose[to]`` (rigid).
    information : (6, 6) array
        Inverse covariance, symmetric positive definite, ordered (tx, ty, tz [1/m^2], rx, ry, rz
        [1/rad^2]); identity by default.
    robust : bool
        Apply the robust loss of :class:`PoseGraphParams` (for loop closures that may be wrong).
    """

    from_: int
    to: int
    measurement: np.ndarray = field(default_factory=lambda: np.eye(4))
    information: np.ndarray = field(default_factory=lambda: np.eye(6))
    robust: bool = False

    def to_core(self) -> _core.PoseGraphEdge:
        measurement = np.asarray(self.measurement, dtype=np.float64)
        information = np.asarray(self.information, dtype=np.float64)
        if measurement.shape != (4, 4):
            raise ValueError(f"edge measurement must be a 4x4 rigid transform, got shape {measurement.shape}")
        if information.shape != (6, 6):
            raise ValueError(f"edge information must be a 6x6 matrix, got shape {information.shape}")
        if int(self.from_) < 0 or int(self.to) < 0:
            raise ValueError(f"edge node indices must be >= 0, got {self.from_} -> {self.to}")
        edge = _core.PoseGraphEdge()
        edge.from_ = int(self.from_)
        edge.to = int(self.to)
        edge.measurement = measurement
        edge.information = information
        edge.robust = bool(self.robust)
        return edge


@dataclass
class PoseGraphParams:
    """Parameters of :func:`optimize_pose_graph`, mirroring ``terracube::PoseGraphParams``.

    Attributes
    ----------
    max_iterations : int
        Levenberg-Marquardt iterations at most, 1 to 10,000.
    robust_loss : {"cauchy", "huber"}
        Loss on robust edges: Cauchy ``a^2 log(1 + s / a^2)`` or Huber (quadratic up to ``a``).
    robust_loss_scale : float
        ``a``, in whitened units (standard deviations of the edge), > 0.
    fixed : sequence of int
        Poses held at their initial value (at least one: the gauge).
    fixed_rotations : sequence of int
        Poses whose rotation is held while the translation is free.
    function_tolerance, gradient_tolerance, parameter_tolerance : float
        Ceres' stopping tolerances.
    num_threads : int
        Ceres' threads (>= 1).
    """

    max_iterations: int = 100
    robust_loss: str = "cauchy"
    robust_loss_scale: float = 1.0
    fixed: Sequence[int] = (0,)
    fixed_rotations: Sequence[int] = ()
    function_tolerance: float = 1e-12
    gradient_tolerance: float = 1e-14
    parameter_tolerance: float = 1e-12
    num_threads: int = 1

    def to_core(self) -> _core.PoseGraphParams:
        losses = {"huber": _core.RobustLoss.huber, "cauchy": _core.RobustLoss.cauchy}
        loss = self.robust_loss
        if not isinstance(loss, _core.RobustLoss):
            if str(loss) not in losses:
                raise ValueError(f"robust_loss must be 'huber' or 'cauchy', got {loss!r}")
            loss = losses[str(loss)]
        for name in ("fixed", "fixed_rotations"):
            if any(int(node) < 0 for node in getattr(self, name)):
                raise ValueError(f"{name} indices must be >= 0, got {list(getattr(self, name))}")
        params = _core.PoseGraphParams()
        params.max_iterations = int(self.max_iterations)
        params.robust_loss = loss
        params.robust_loss_scale = float(self.robust_loss_scale)
        params.fixed = [int(node) for node in self.fixed]
        params.fixed_rotations = [int(node) for node in self.fixed_rotations]
        params.function_tolerance = float(self.function_tolerance)
        params.gradient_tolerance = float(self.gradient_tolerance)
        params.parameter_tolerance = float(self.parameter_tolerance)
        params.num_threads = int(self.num_threads)
        return params


def _core_edge(edge) -> _core.PoseGraphEdge:
    if isinstance(edge, _core.PoseGraphEdge):
        return edge
    if isinstance(edge, PoseGraphEdge):
        return edge.to_core()
    if isinstance(edge, tuple):
        return PoseGraphEdge(*edge).to_core()
    raise TypeError(
        "an edge must be a PoseGraphEdge or a (from_, to, measurement[, information[, robust]]) tuple, "
        f"got {type(edge).__name__}"
    )


def optimize_pose_graph(
    poses, edges: Iterable, params: PoseGraphParams | None = None, **kwargs
) -> PoseGraphResult:
    """Optimises the poses of a pose graph (Levenberg-Marquardt, sparse Cholesky; GIL released).

    Parameters
    ----------
    poses : (K, 4, 4) array
        Initial rigid poses (e.g. chained odometry).
    edges : iterable of PoseGraphEdge or (from_, to, measurement[, information[, robust]]) tuples
    params : PoseGraphParams, optional
        Otherwise built from ``kwargs``.

    Returns
    -------
    PoseGraphResult
        ``poses`` (K, 4, 4), ``initial_cost``, ``final_cost`` (1/2 sum of the squared whitened
        residuals, robustified), ``iterations``, ``converged``, ``message``.

    Raises
    ------
    ValueError
        No poses, a wrong shape, non-finite or non-rigid poses or measurements, node indices out
        of range, an information matrix that is not symmetric positive definite, bad parameters.
    """
    params = params or PoseGraphParams(**kwargs)
    core_edges = [_core_edge(edge) for edge in edges]
    return _core.optimize_pose_graph(np.asarray(poses), core_edges, params.to_core())
