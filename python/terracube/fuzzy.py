"""Fuzzy elevation maps (FEM): an ANFIS-identified Takagi-Sugeno surface z = f(x, y).

[CBC] builds, beside the DEM, a fuzzy
elevation map that filters sensor noise and interpolates small shadowed areas. The model and the
hybrid learning are documented in ``cpp/include/terracube/fuzzy.hpp``: 19 x 10 zero-order rules
over a grid of membership functions (one free centre each) give the paper's 190 + 29 = 219
parameters; the consequents come from ridge least squares, the centres from gradient steps.

Example
-------
>>> dem, collapse = tc.dem_without_overhangs(xyz, sigma=5)
>>> fem = tc.FuzzyElevationMap.fit(xyz, use=~collapse.overhang, extent=((0, -5), (20, 5)))
>>> fem.to_layer(dem)                  # adds "fem" and "fem_confidence"
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from . import _core
from .collapse import _as_points, _as_use_mask, _checked
from .elevation import ElevationMap

__all__ = ["FuzzyParams", "FuzzyElevationMap", "fit_fuzzy_elevation_map"]

_FAMILIES = {"triangular": _core.MembershipFamily.triangular, "gaussian": _core.MembershipFamily.gaussian}


@dataclass
class FuzzyParams:
    """Parameters of :func:`fit_fuzzy_elevation_map`, mirroring ``terracube::FuzzyParams``.

    Attributes
    ----------
    rules_x, rules_y : int
        Membership functions along x and y (>= 2); rules = rules_x * rules_y (19 x 10, the paper).
    membership : {"triangular", "gaussian"}
        Triangles forming a partition of unity (f is the bilinear interpolation of the rule
        consequents over the movable centre grid), or normalised Gaussians of fixed width.
    gaussian_width : float
        Gaussian width as a fraction of the initial centre spacing (0.5).
    epochs : int
        Hybrid-learning epochs, 0 to 100000; 0 = least squares only on uniformly spaced centres (10).
    learning_rate : float
        Initial gradient step as a fraction of the smaller centre spacing (0.1).
    ridge : float
        Ridge weight (times points per rule) pulling rules with little data to the mean height.
    smoothness : float
        Weight (times points per rule) of the squared differences between neighbouring rules'
        consequents: keeps sparsely supported rules from overshooting (0.05).
    extent : ((x_min, y_min), (x_max, y_max)) or None
        Area fitted [m]; None: the points' bounding box. Points outside take no part.
    min_points_per_rule : float
        The fit needs at least this many points per rule on average (2).
    min_confidence : float
        :meth:`FuzzyElevationMap.to_layer` leaves cells with less rule support empty [points] (3).
    step_rule : {"guarded", "jang"}
        ``"guarded"``: a centre step is kept only if the training error does not grow (step +10 %),
        else retried at half the step. ``"jang"``: every step is taken and the step adapts by
        Jang's heuristic (+10 % after four error reductions in a row, -10 % after two
        increase-reduction alternations): plain ANFIS, with ``ridge=0, smoothness=0``.
    """

    rules_x: int = 19
    rules_y: int = 10
    membership: str = "triangular"
    gaussian_width: float = 0.5
    epochs: int = 10
    learning_rate: float = 0.1
    ridge: float = 1e-4
    smoothness: float = 0.05
    extent: Sequence[Sequence[float]] | None = None
    min_points_per_rule: float = 2.0
    min_confidence: float = 3.0
    step_rule: str = "guarded"

    def to_core(self) -> _core.FuzzyParams:
        if self.membership not in _FAMILIES:
            raise ValueError(f"membership must be one of {sorted(_FAMILIES)}, got {self.membership!r}")
        params = _checked(_core.FuzzyParams)()
        params.rules_x = int(self.rules_x)
        params.rules_y = int(self.rules_y)
        params.membership = _FAMILIES[self.membership]
        params.gaussian_width = float(self.gaussian_width)
        params.epochs = int(self.epochs)
        params.learning_rate = float(self.learning_rate)
        params.ridge = float(self.ridge)
        params.smoothness = float(self.smoothness)
        if self.extent is not None:
            extent = np.asarray(self.extent, dtype=np.float64)
            if extent.shape != (2, 2):
                raise ValueError(f"extent must be ((x_min, y_min), (x_max, y_max)), got {self.extent!r}")
            params.set_extent(*extent[0], *extent[1])
        params.min_points_per_rule = float(self.min_points_per_rule)
        params.min_confidence = float(self.min_confidence)
        rules = {"guarded": _core.StepRule.guarded, "jang": _core.StepRule.jang}
        if self.step_rule not in rules:
            raise ValueError(f"step_rule must be one of {sorted(rules)}, got {self.step_rule!r}")
        params.step_rule = rules[self.step_rule]
        params.check()  # the core's own ranges, before any scan (and in a config file)
        return params

    @classmethod
    def from_core(cls, core: _core.FuzzyParams) -> FuzzyParams:
        return cls(
            rules_x=core.rules_x,
            rules_y=core.rules_y,
            membership=core.membership.name,
            gaussian_width=core.gaussian_width,
            epochs=core.epochs,
            learning_rate=core.learning_rate,
            ridge=core.ridge,
            smoothness=core.smoothness,
            min_points_per_rule=core.min_points_per_rule,
            min_confidence=core.min_confidence,
            step_rule=core.step_rule.name,
        )


def _xy(points) -> np.ndarray:
    """(N, 2) C-contiguous float64 x, y from an (N, 2) or (N, 3+) array."""
    array = np.asarray(points)
    if array.ndim != 2 or array.shape[1] < 2:
        raise ValueError(f"points must be an (N, 2) or (N, 3) array, got shape {array.shape}")
    return np.ascontiguousarray(array[:, :2], dtype=np.float64)


class FuzzyElevationMap:
    """A fitted fuzzy elevation surface; see :func:`fit_fuzzy_elevation_map`.

    Arrays: ``centers_x`` (rules_x,), ``centers_y`` (rules_y,) [m]; ``consequents`` and
    ``rule_support`` (rules_x, rules_y), the rule heights [m] and the summed firing strengths of
    the training points [points]; ``rmse_history`` the training RMSE [m] after the initial least
    squares and after each epoch.
    """

    def __init__(self, core: _core.FuzzyElevationMap):
        self._core = core

    def __reduce__(self):
        """Pickles as its parts and training record (worker processes, copy.deepcopy)."""
        parts = (self.params, self.centers_x, self.centers_y, self.consequents, self.rule_support)
        return _restored, (*parts, self.rmse_history, self.num_training_points)

    @classmethod
    def fit(cls, points, params: FuzzyParams | None = None, *, use=None, **kwargs) -> FuzzyElevationMap:
        """Same as :func:`fit_fuzzy_elevation_map`."""
        return fit_fuzzy_elevation_map(points, params, use=use, **kwargs)

    @classmethod
    def from_parameters(
        cls,
        centers_x,
        centers_y,
        consequents,
        extent,
        *,
        membership: str = "triangular",
        rule_support=None,
        **kwargs,
    ) -> FuzzyElevationMap:
        """A surface with explicit centres [m] and (rules_x, rules_y) consequents [m] over ``extent``."""
        params = FuzzyParams(membership=membership, extent=extent, **kwargs).to_core()
        consequents = np.asarray(consequents, dtype=np.float64)
        support = np.zeros_like(consequents) if rule_support is None else np.asarray(rule_support, np.float64)
        return cls(
            _core.FuzzyElevationMap(
                params,
                np.asarray(centers_x, np.float64),
                np.asarray(centers_y, np.float64),
                consequents,
                support,
            )
        )

    @property
    def params(self) -> FuzzyParams:
        params = FuzzyParams.from_core(self._core.params)
        params.extent = tuple(tuple(float(v) for v in corner) for corner in self.extent)
        return params

    @property
    def extent(self) -> np.ndarray:
        """((x_min, y_min), (x_max, y_max)) [m]."""
        return self._core.extent

    @property
    def num_rules(self) -> int:
        return self._core.num_rules

    @property
    def num_parameters(self) -> int:
        """Consequents plus one centre per membership function (219 for 19 x 10)."""
        return self._core.num_parameters

    @property
    def centers_x(self) -> np.ndarray:
        return self._core.centers_x

    @property
    def centers_y(self) -> np.ndarray:
        return self._core.centers_y

    @property
    def consequents(self) -> np.ndarray:
        return self._core.consequents

    @property
    def rule_support(self) -> np.ndarray:
        return self._core.rule_support

    @property
    def rmse_history(self) -> np.ndarray:
        return np.asarray(self._core.rmse_history)

    @property
    def num_training_points(self) -> int:
        return self._core.num_training_points

    def evaluate(self, points) -> np.ndarray:
        """(N,) heights f(x, y) [m] at the rows of an (N, 2) or (N, 3) array (z ignored)."""
        return self._core.evaluate(_xy(points))

    def confidence(self, points) -> np.ndarray:
        """(N,) rule support at (x, y) [points]: sum of firing strength * rule support; 0 outside."""
        return self._core.confidence(_xy(points))

    def to_layer(
        self, elevation_map: ElevationMap, min_confidence: float | None = None, name: str = "fem"
    ) -> None:
        """Add ``name`` (f at the cell centres, NaN below ``min_confidence``) and ``name_confidence``."""
        threshold = -1.0 if min_confidence is None else float(min_confidence)
        if min_confidence is not None and not threshold >= 0:
            raise ValueError(f"min_confidence must be >= 0 [points], got {min_confidence!r}")
        self._core.to_layer(elevation_map._core, threshold, name)

    def __repr__(self) -> str:
        e = self.extent
        rmse = self.rmse_history
        fit = f", rmse={rmse[-1]:.4f} m after {len(rmse) - 1} epochs" if len(rmse) else ""
        family = self._core.params.membership.name
        return (
            f"FuzzyElevationMap({len(self.centers_x)}x{len(self.centers_y)} {family} rules, "
            f"{self.num_parameters} parameters, extent=({e[0, 0]:.2f}, {e[0, 1]:.2f})..({e[1, 0]:.2f}, "
            f"{e[1, 1]:.2f}), {self.num_training_points} points{fit})"
        )


def _restored(params, centers_x, centers_y, consequents, rule_support, rmse_history, num_training_points):
    """The map of a pickled state (FuzzyElevationMap.__reduce__)."""
    core = _core.FuzzyElevationMap(
        params.to_core(),
        centers_x,
        centers_y,
        consequents,
        rule_support,
        list(rmse_history),
        num_training_points,
    )
    return FuzzyElevationMap(core)


def fit_fuzzy_elevation_map(
    points, params: FuzzyParams | None = None, *, use=None, **kwargs
) -> FuzzyElevationMap:
    """Identify a fuzzy elevation map from a cloud by ANFIS hybrid learning (GIL released).

    Parameters
    ----------
    points : (N, 3) or wider float32 or float64 array
        x, y, z [m] in the first three columns, in the frame of the map (apply any leveling transform first).
    params : FuzzyParams, optional
        Or its fields as keyword arguments.
    use : (N,) bool (or whole numbers 0 and 1), optional
        Only these points take part, e.g. ``~collapse.overhang`` for the points collapsible cubes kept.

    Returns
    -------
    FuzzyElevationMap
        ``evaluate((K, 2) x, y [m])`` gives (K,) heights [m]; ``to_layer(map)`` adds the ``fem``
        and ``fem_confidence`` layers; ``rmse_history`` [m] per epoch.

    Raises
    ------
    ValueError
        Bad parameters, NaN/Inf rows, too few points for the rule grid.
    """
    if params is None:
        params = FuzzyParams(**kwargs)
    elif kwargs:
        raise TypeError("give params or keyword arguments, not both")
    use_flags = _as_use_mask(use)
    return FuzzyElevationMap(_core.fit_fuzzy_elevation_map(_as_points(points), params.to_core(), use_flags))
