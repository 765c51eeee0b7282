"""Collapsible cubes on real KITTI scans, judged by SemanticKITTI labels (frames 000000-000002).

A robot of height 2.5 m at E = 0.5 m gives σ = sigma_from_robot_height(2.5, 0.5) = 5. The road
is at about z = -1.73 m in the sensor frame; KITTI also has multipath reflections below the road
down to z = -11 m, which the crop z >= -3 m drops.
"""

from __future__ import annotations

import numpy as np
import pytest
import terracube as tc

EDGE = 0.5
ROBOT_HEIGHT = 2.5
CROP = ((-100.0, -100.0, -3.0), (100.0, 100.0, 30.0))
FRAMES = (0, 1, 2)

UNLABELED, CAR, ROAD, PARKING, SIDEWALK, BUILDING, VEGETATION, TRUNK = 0, 10, 40, 44, 48, 50, 70, 71
NEVER_REMOVED = {"road": ROAD, "sidewalk": SIDEWALK, "parking": PARKING, "car": CAR, "building": BUILDING}


def removed_per_class(shared_data, crop) -> dict:
    """Removed (overhang) points per SemanticKITTI class, summed over FRAMES."""
    sigma = tc.sigma_from_robot_height(ROBOT_HEIGHT, EDGE)
    assert sigma == 5
    counts: dict = {}
    for frame in FRAMES:
        xyz = shared_data.kitti_xyzi(frame)[:, :3]
        labels = shared_data.kitti_labels(frame)
        assert len(labels) == len(xyz)
        result = tc.collapse_overhangs(xyz, edge=EDGE, sigma=sigma, crop=crop)
        classes, numbers = np.unique(labels[result.overhang], return_counts=True)
        for label, number in zip(classes.tolist(), numbers.tolist(), strict=True):
            counts[label] = counts.get(label, 0) + number
    return counts


def test_removed_points_are_vegetation_and_never_road_sidewalk_parking_car_or_building(shared_data):
    """Measured over frames 0-2 with the crop: 469 points removed, vegetation (70) 361,
    trunk (71) 70, unlabeled (0) 38, and zero road (40), sidewalk (48), parking (44), car (10)
    and building (50)."""
    counts = removed_per_class(shared_data, CROP)
    total = sum(counts.values())
    print(f"removed points per SemanticKITTI class over frames {FRAMES}: {dict(sorted(counts.items()))}")
    assert total > 300, "the test must not pass by removing nothing"
    for name, label in NEVER_REMOVED.items():
        assert counts.get(label, 0) == 0, f"{counts.get(label, 0)} {name} points removed"
    canopy = counts.get(VEGETATION, 0) + counts.get(TRUNK, 0)
    assert canopy >= 0.9 * total, f"only {canopy} of {total} removed points are vegetation or trunk"


def test_without_the_crop_reflections_below_the_road_become_ground_and_road_points_are_removed(
    shared_data,
):
    """Documents why the crop is needed. KITTI's multipath returns below the road (down to
    z = -11 m) are the lowest cube of their column, so they become its ground; the real road
    surface then sits σ or more empty cubes above that false ground and collapses. Measured over
    frames 0-2 without the crop: road 10, sidewalk 22 points removed."""
    sigma = tc.sigma_from_robot_height(ROBOT_HEIGHT, EDGE)
    removed_ground = 0
    for frame in FRAMES:
        xyz = shared_data.kitti_xyzi(frame)[:, :3]
        labels = shared_data.kitti_labels(frame)
        result = tc.collapse_overhangs(xyz, edge=EDGE, sigma=sigma)
        grid = result.grid
        cube = np.floor((xyz.astype(np.float64) - grid.min_corner) * (1.0 / EDGE) + 0.5).astype(np.int64)
        column = cube[:, 0] + cube[:, 1] * grid.ixmax
        for row in np.flatnonzero(result.overhang & np.isin(labels, [ROAD, SIDEWALK])):
            # The column's ground is a reflection below the crop floor, far under the road.
            lowest = xyz[column == column[row], 2].min()
            assert lowest < CROP[0][2], f"frame {frame} row {row}: lowest point of its column at {lowest} m"
            removed_ground += 1
        # With the crop the same frame loses no road or sidewalk point.
        cropped = tc.collapse_overhangs(xyz, edge=EDGE, sigma=sigma, crop=CROP)
        assert not (cropped.overhang & np.isin(labels, [ROAD, SIDEWALK])).any()
    counts = removed_per_class(shared_data, None)
    assert counts.get(ROAD, 0) > 0
    assert removed_ground == counts.get(ROAD, 0) + counts.get(SIDEWALK, 0)


# ------------------------------------------------------------------ method="shadow_aware" (issue 34)

GROUND_LABELS = (40, 44, 48, 49, 72)  # road, parking, sidewalk, other-ground, terrain
FENCE, POLE = 51, 80
SHADOW_AWARE_NEVER = {"road": ROAD, "sidewalk": SIDEWALK, "parking": PARKING, "car": CAR, "pole": POLE}
STRUCTURE = (BUILDING, FENCE, TRUNK)


def canopy_of(xyz: np.ndarray, labels: np.ndarray) -> np.ndarray:
    """Vegetation more than 2.5 m above the local ground: the median z of the 8 nearest
    ground-labelled points in x, y, when the nearest lies within 3 m (bench/bench_shadow_aware.py)."""
    spatial = pytest.importorskip("scipy.spatial")
    ground = np.isin(labels, GROUND_LABELS)
    vegetation = np.flatnonzero(labels == VEGETATION)
    distance, index = spatial.cKDTree(xyz[ground, :2]).query(xyz[vegetation, :2], k=8)
    height = np.median(xyz[ground, 2][index], axis=1)
    canopy = np.zeros(len(xyz), bool)
    canopy[vegetation] = (distance[:, 0] <= 3.0) & (xyz[vegetation, 2] - height > 2.5)
    return canopy


def height_above_ground(xyz: np.ndarray, labels: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """The height of `rows` above the median z of the 8 nearest ground-labelled points in x, y."""
    spatial = pytest.importorskip("scipy.spatial")
    ground = np.isin(labels, GROUND_LABELS)
    _, index = spatial.cKDTree(xyz[ground, :2]).query(xyz[rows, :2], k=8)
    return xyz[rows, 2] - np.median(xyz[ground, 2][index], axis=1)


@pytest.mark.parametrize(
    ("sigma", "recall_floor", "structure_ceiling"), [(4, 0.46, 0.0055), (5, 0.275, 0.005)]
)
def test_shadow_aware_removes_canopy_without_crop_and_no_road_sidewalk_parking_car_or_pole(
    shared_data, sigma, recall_floor, structure_ceiling
):
    """Frames 0-2, E = 0.5 m, no crop (multipath below the road decides nothing). Measured with the
    defaults: canopy recall 0.464 at σ 4 and 0.280 at σ 5 (the paper's rule with the crop: 0.12
    and 0.06); road, sidewalk, parking, car and pole: 0; building + fence + trunk removed 0.53 % and
    0.23 %. The issue's 0.5 recall is not reached (docs/performance.md says why). Of the structure,
    the rims (remove_rims) add only points labelled trunk that lie more than 2.5 m above the
    labelled ground (tops of trunks whose middle is unseen, 31 at σ 4, the lowest 2.7 m up), no
    building or fence point; without them 0.48 % and 0.20 %."""
    canopy_total = canopy_removed = paper_removed = structure_total = structure_removed = 0
    never = dict.fromkeys(SHADOW_AWARE_NEVER, 0)
    without_rims = tc.CollapseParams(edge=EDGE, sigma=sigma, method="shadow_aware", remove_rims=False)
    for frame in FRAMES:
        xyz = shared_data.kitti_xyzi(frame)[:, :3]
        labels = shared_data.kitti_labels(frame)
        canopy = canopy_of(xyz.astype(np.float64), labels)
        removed = tc.collapse_overhangs(xyz, EDGE, sigma, method="shadow_aware").overhang
        paper = tc.collapse_overhangs(xyz, EDGE, sigma, crop=CROP).overhang
        canopy_total += int(canopy.sum())
        canopy_removed += int((canopy & removed).sum())
        paper_removed += int((canopy & paper).sum())
        for name, label in SHADOW_AWARE_NEVER.items():
            never[name] += int((removed & (labels == label)).sum())
        structure = np.isin(labels, STRUCTURE)
        structure_total += int(structure.sum())
        structure_removed += int((removed & structure).sum())
        by_rims = removed & ~tc.collapse_overhangs(xyz, params=without_rims).overhang
        assert not (by_rims & np.isin(labels, (BUILDING, FENCE))).any()
        assert (height_above_ground(xyz.astype(np.float64), labels, by_rims & (labels == TRUNK)) > 2.5).all()
    recall = canopy_removed / canopy_total
    print(
        f"σ {sigma}: canopy recall {recall:.3f} (paper + crop {paper_removed / canopy_total:.3f}), "
        f"structure removed {100 * structure_removed / structure_total:.3f} %, never-removed {never}"
    )
    assert canopy_total > 5000
    assert recall >= recall_floor
    assert canopy_removed >= 3 * paper_removed
    assert never == dict.fromkeys(SHADOW_AWARE_NEVER, 0)
    assert structure_removed <= structure_ceiling * structure_total
