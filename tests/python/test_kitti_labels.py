"""Collapsible cubes on real KITTI scans, judged by SemanticKITTI labels (frames 000000-000002).

A robot of height 2.5 m at E = 0.5 m gives σ = sigma_from_robot_height(2.5, 0.5) = 5. The road
is at about z = -1.73 m in the sensor frame; KITTI also has multipath reflections below the road
down to z = -11 m, which the crop z >= -3 m drops.
"""

from __future__ import annotations

import numpy as np
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
