"""collapse_overhangs(method="shadow_aware"): the rule for columns whose ground the sensor cannot see.

Every result is checked against `naive_shadow_aware` below, a plain transcription of the rule in
terracube/shadow_aware.hpp (dicts and loops, no shared code with the C++), and the hand-made
columns check the behaviour each case needs: a wall whose foot is hidden stays, a crown over a curb
goes, a tunnel ceiling over a lit floor goes, and a multipath point under the road decides nothing.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import terracube as tc
from terracube.collapse import CubeReason
from terracube.io import load_sample_scan

SUPPORTED, BELOW_GROUND, NO_GROUND, SHADOWED, ABOVE_KEPT, FREE_BELOW, THIN, RIM = range(8)
REMOVED = (ABOVE_KEPT, FREE_BELOW, RIM)
MAKES_RIMS = (FREE_BELOW, RIM)  # removals of chains judged wide (or rims of them)


def pseudo_angle(dx: float, dy: float) -> float:
    if dy >= 0.0:
        return dy / (dx + dy) if dx >= 0.0 else 1.0 - dx / (-dx + dy)
    return 2.0 - dy / (-dx - dy) if dx < 0.0 else 3.0 + dx / (dx - dy)


def naive_shadow_aware(
    grid,
    occupied,
    points,
    sigma,
    origin,
    radius=5.0,
    support=4,
    sectors=512,
    margin=0.25,
    neighbours=4,
    window=2,
    hidden=2.0,
    no_returns=(),
    no_return_range=30.0,
    rims=True,
) -> list[int]:
    """The reason of every cube of `occupied` (sorted cube indices I of `grid`), computed plainly
    from the leveled `points` that took part and the leveled directions of the beams without a
    return (`no_returns`)."""
    nx, ny = grid.ixmax, grid.iymax
    columns = nx * ny
    edge, corner = grid.edge, grid.min_corner
    layers: dict[tuple[int, int], list[int]] = {}
    for cube in occupied:
        column = int(cube) % columns
        layers.setdefault((column % nx, column // nx), []).append(int(cube) // columns)
    lowest = {key: min(values) for key, values in layers.items()}
    # 1. reliable ground: `support` columns of the 3x3 block have their lowest cube within a layer,
    # and more of them than have theirs sigma or more layers above
    reliable = {}
    for (ix, iy), layer in lowest.items():
        block = [lowest.get((ix + dx, iy + dy)) for dx in (-1, 0, 1) for dy in (-1, 0, 1)]
        near = sum(1 for other in block if other is not None and abs(other - layer) <= 1)
        far = sum(1 for other in block if other is not None and other - layer >= sigma)
        if near >= support and near > far:
            reliable[(ix, iy)] = layer

    # 1b. reliable ground under the line of sight over nearer reliable ground below the sensor, by
    # more than `hidden`, is no ground
    def centre(ix, iy, iz):
        return corner[0] + edge * ix, corner[1] + edge * iy, corner[2] + edge * iz

    def sector_and_step(x, y):
        dx, dy = x - origin[0], y - origin[1]
        distance = math.sqrt(dx * dx + dy * dy)
        sector = min(sectors - 1, int(pseudo_angle(dx, dy) / 4.0 * sectors)) if distance > 0 else None
        return sector, int(distance * (1.0 / edge)) if distance > 0 else None, distance

    def bottom_face(layer):
        return corner[2] + (layer - 0.5) * edge

    placed = {key: sector_and_step(*centre(*key, 0)[:2]) for key in reliable}
    limits: dict[int, list[tuple[int, float]]] = {}  # per sector: (step, slope of the sight line's limit)
    for key, layer in reliable.items():
        sector, step, distance = placed[key]
        if sector is not None and bottom_face(layer) < origin[2]:
            limits.setdefault(sector, []).append((step, (bottom_face(layer) - hidden - origin[2]) / distance))

    def hidden_under_nearer_ground(key, layer):
        sector, step, distance = placed[key]
        if sector is None:
            return False
        slope = (bottom_face(layer) + edge - origin[2]) / distance  # to the top face
        return any(other < step and slope < limit for other, limit in limits.get(sector, []))

    reliable = {key: layer for key, layer in reliable.items() if not hidden_under_nearer_ground(key, layer)}
    # 2. G0: the lowest reliable ground in the square window
    reach = math.ceil(radius / edge - 1e-9)

    def window_minimum(candidates, ix, iy):
        found = [
            candidates[(x, y)]
            for x in range(ix - reach, ix + reach + 1)
            for y in range(iy - reach, iy + reach + 1)
            if (x, y) in candidates
        ]
        return min(found) if found else None

    first_ground = {key: window_minimum(reliable, *key) for key in layers}

    # 3. rays to the points whose cube is not below its column's G0 - 1
    rays = []
    for x, y, z in np.asarray(points, dtype=np.float64).tolist():
        ix, iy, iz = (
            int(math.floor((v - c) * (1.0 / edge) + 0.5)) for v, c in zip((x, y, z), corner, strict=True)
        )
        g = first_ground[(ix, iy)]
        if g is None or iz >= g - 1:
            sector, step, distance = sector_and_step(x, y)
            if sector is not None:
                rays.append((sector, step, (z - origin[2]) / distance))
    # ... and the beams without a return at or above the horizon, which end no_return_range out
    # (each scaled by its largest component first, as the core does against overflow)
    for direction in np.asarray(no_returns, dtype=np.float64).reshape(-1, 3).tolist():
        largest = max(abs(v) for v in direction)
        dx, dy, dz = (v / largest for v in direction)
        horizontal = math.sqrt(dx * dx + dy * dy)
        if dz >= 0.0 and horizontal > 0.0:
            end = no_return_range * horizontal / math.sqrt(dx * dx + dy * dy + dz * dz)
            sector = min(sectors - 1, int(pseudo_angle(dx, dy) / 4.0 * sectors))
            rays.append((sector, int(end * (1.0 / edge)), dz / horizontal))
    rays = np.array(rays, dtype=np.float64).reshape(-1, 3)

    def free_floor(ix, iy):
        x, y, _ = centre(ix, iy, 0)
        sector, step, distance = sector_and_step(x, y)
        if sector is None:
            return math.inf
        slopes = rays[(rays[:, 0] == sector) & (rays[:, 1] > step), 2]
        return origin[2] + slopes.min() * distance if slopes.size else math.inf

    # a reliable lowest cube with a ray under it is no ground; G from the others
    reliable = {key: layer for key, layer in reliable.items() if not free_floor(*key) < bottom_face(layer)}
    ground = {key: window_minimum(reliable, *key) for key in layers}

    # 4. chains bottom-up
    def chains_of(column_layers):
        chains = [[column_layers[0]]]
        for layer in column_layers[1:]:
            if layer - chains[-1][-1] - 1 < sigma:
                chains[-1].append(layer)
            else:
                chains.append([layer])
        return chains

    chains_by_column = {key: chains_of(column_layers) for key, column_layers in layers.items()}

    def floats(key, layer):
        """Whether the chain holding `layer` of column `key` starts σ or more empty cubes above its G."""
        chain = next(chain for chain in chains_by_column[key] if layer in chain)
        return ground[key] is not None and chain[0] - ground[key] - 1 >= sigma

    def wide_below(ix, iy, bottom):
        """Whether `neighbours` of the 8 columns around hold a cube within one layer of `bottom`, or,
        with no grounded chain there among those 8, as many columns of the window a floating one."""
        beside = floating = 0
        grounded_beside = False
        for dx in range(-window, window + 1):
            for dy in range(-window, window + 1):
                near = [layer for layer in layers.get((ix + dx, iy + dy), []) if abs(layer - bottom) <= 1]
                if not (dx or dy) or not near:
                    continue
                adjacent = abs(dx) <= 1 and abs(dy) <= 1
                chain_floats = floats((ix + dx, iy + dy), near[0])
                beside += adjacent
                floating += chain_floats
                grounded_beside = grounded_beside or (adjacent and not chain_floats)
        return beside >= neighbours or (not grounded_beside and floating >= neighbours)

    reason_of: dict[tuple[int, int, int], int] = {}
    for (ix, iy), chains in chains_by_column.items():
        g = ground[(ix, iy)]
        kept_below = False
        for chain in chains:
            bottom, top = chain[0], chain[-1]
            if g is None:
                reason = NO_GROUND
            elif top < g:
                reason = BELOW_GROUND
            elif bottom - g - 1 < sigma:
                reason = SUPPORTED
            elif kept_below:
                reason = ABOVE_KEPT
            elif not wide_below(ix, iy, bottom):
                reason = THIN
            elif free_floor(ix, iy) < bottom_face(bottom) - margin:
                reason = FREE_BELOW
            else:
                reason = SHADOWED
            kept_below = kept_below or reason in (SUPPORTED, SHADOWED, THIN, NO_GROUND)
            for layer in chain:
                reason_of[(ix, iy, layer)] = reason

    # 5. rims: a thin chain with, among the 8 columns around, a cube of a removed wide chain or rim
    # within one layer of its bottom, and no more columns with a supported one there than with such a
    # removed one
    def reasons_near(key, bottom):
        return [reason_of[(*key, layer)] for layer in layers.get(key, []) if abs(layer - bottom) <= 1]

    changed = rims
    while changed:
        changed = False
        for (ix, iy), chains in chains_by_column.items():
            for chain in chains:
                if reason_of[(ix, iy, chain[0])] != THIN:
                    continue
                around = [
                    reasons_near((ix + dx, iy + dy), chain[0])
                    for dx in (-1, 0, 1)
                    for dy in (-1, 0, 1)
                    if dx or dy
                ]
                removed = sum(any(r in MAKES_RIMS for r in near) for near in around)
                grounded = sum(SUPPORTED in near for near in around)
                if removed and removed >= grounded:
                    reason = RIM if free_floor(ix, iy) < bottom_face(chain[0]) - margin else SHADOWED
                    for layer in chain:
                        reason_of[(ix, iy, layer)] = reason
                    changed = True
    out = []
    for cube in occupied:
        column = int(cube) % columns
        out.append(reason_of[(column % nx, column // nx, int(cube) // columns)])
    return out


def shadow_aware(points, sigma=4, edge=0.5, **kwargs):
    return tc.collapse_overhangs(np.asarray(points, float), edge, sigma, method="shadow_aware", **kwargs)


def leveled(points, transform) -> np.ndarray:
    """q_i = ((r_i0 x + r_i1 y) + r_i2 z) + t_i, the order the core uses."""
    p = np.asarray(points, dtype=np.float64)
    t = np.asarray(transform, dtype=np.float64)
    return np.column_stack(
        [t[i, 0] * p[:, 0] + t[i, 1] * p[:, 1] + t[i, 2] * p[:, 2] + t[i, 3] for i in range(3)]
    )


def check_against_naive(result, points, sigma, origin=(0.0, 0.0, 0.0), **kwargs) -> np.ndarray:
    """Asserts the C++ reasons, removed cubes and mask equal the naive rule's; returns the reasons."""
    expected = np.array(
        naive_shadow_aware(result.grid, result.occupied_cubes, points, sigma, origin, **kwargs)
    )
    reasons = np.asarray(result.cube_reasons)
    assert reasons.shape == result.occupied_cubes.shape
    np.testing.assert_array_equal(reasons, expected)
    np.testing.assert_array_equal(result.removed_cubes, result.occupied_cubes[np.isin(expected, REMOVED)])
    return reasons


def ground_patch(x0, x1, y0, y1, z=-1.7, step=0.25):
    xs, ys = np.meshgrid(np.arange(x0, x1, step), np.arange(y0, y1, step))
    return np.column_stack([xs.ravel(), ys.ravel(), np.full(xs.size, z)])


def vertical_face(x, y0, y1, z0, z1, step=0.2):
    ys, zs = np.meshgrid(np.arange(y0, y1, step), np.arange(z0, z1, step))
    return np.column_stack([np.full(ys.size, x), ys.ravel(), zs.ravel()])


def slab(x0, x1, y0, y1, z, step=0.25):
    return ground_patch(x0, x1, y0, y1, z, step)


def reasons_of_points(result, points) -> np.ndarray:
    """The reason of the cube holding each point."""
    grid = result.grid
    cube = np.floor((np.asarray(points, float) - grid.min_corner) / grid.edge + 0.5).astype(np.int64)
    index = cube[:, 0] + cube[:, 1] * grid.ixmax + cube[:, 2] * grid.ixmax * grid.iymax
    return np.asarray(result.cube_reasons)[np.searchsorted(result.occupied_cubes, index)]


# ------------------------------------------------------------------------------ hand-made columns


def test_wall_whose_foot_is_hidden_behind_a_car_stays():
    """Sensor at the origin, σ = 2 (a 1 m robot); road up to a car (x 6-8, 1.5 m tall) that hides
    the road behind it and the foot of a wall at x = 8.5: the wall is seen from 1.5 m up only, 3
    layers above the road, and no ray passes under it (the car stops them), so it is shadowed and
    kept (its two end columns are thin: fewer than 4 columns around their bottom)."""
    ground = ground_patch(1, 6, -4, 4)
    car = np.vstack([vertical_face(6.0, -2, 2, -1.7, -0.2), slab(6, 8, -2, 2, -0.2)])
    wall = vertical_face(8.5, -2, 2, -0.2, 3.0)
    points = np.vstack([ground, car, wall])
    result = shadow_aware(points, sigma=2)
    check_against_naive(result, points, 2)
    wall_reasons = reasons_of_points(result, wall)
    assert (wall_reasons[np.abs(wall[:, 1]) < 1.5] == SHADOWED).all()
    assert np.isin(wall_reasons, (SHADOWED, THIN)).all()
    assert not result.overhang.any()
    # without the car, rays to the road behind pass under the column at y = 0: it floats (a sign)
    behind = ground_patch(10, 14, -0.5, 0.5)
    lit = np.vstack([ground, wall, behind])
    lit_result = shadow_aware(lit, sigma=2)
    check_against_naive(lit_result, lit, 2)
    assert (reasons_of_points(lit_result, wall[wall[:, 1] == 0.0]) == FREE_BELOW).all()


def test_crown_over_a_curb_goes_while_its_trunk_stays():
    """A 0.3 m curb at x = 5 hides the ground behind it; a tree at x = 9 (trunk to 3.2 m, crown
    3.2-5.5 m, 2.5 m across) is seen over it; ground far behind (x 14-20) is lit by rays that pass
    under the crown. The crown goes (removed_free_below), the trunk and curb stay; the paper's
    rule removes nothing (no ground in the crown's columns)."""
    ground = np.vstack([ground_patch(1, 5, -5, 5), ground_patch(14, 20, -5, 5)])
    curb = np.vstack([vertical_face(5.0, -5, 5, -1.7, -1.4), slab(5, 5.5, -5, 5, -1.4)])
    trunk = vertical_face(9.0, -0.2, 0.2, -1.4, 1.5, step=0.1)
    crown = np.vstack([slab(7.75, 10.25, -1.25, 1.25, z) for z in (1.6, 2.4, 3.2, 3.8)])
    points = np.vstack([ground, curb, trunk, crown])
    result = shadow_aware(points)
    check_against_naive(result, points, 4)
    crown_reasons = reasons_of_points(result, crown)
    trunk_columns = (np.abs(crown[:, 0] - 9.0) < 0.3) & (np.abs(crown[:, 1]) < 0.3)
    inner = (np.abs(crown[:, 0] - 9.0) < 0.6) & (np.abs(crown[:, 1]) < 0.6)
    assert (crown_reasons[inner & ~trunk_columns] == FREE_BELOW).all()
    assert np.isin(crown_reasons[~trunk_columns], (FREE_BELOW, THIN)).all()  # thin: the corners
    assert (crown_reasons == FREE_BELOW).mean() > 0.7
    assert np.isin(reasons_of_points(result, np.vstack([curb, trunk, ground])), (SUPPORTED,)).all()
    assert not tc.collapse_overhangs(points, 0.5, 4).overhang.any()


def test_a_crowns_rim_beside_its_trunk_goes_the_top_of_a_post_beside_an_arm_stays():
    """σ = 4; a curb at x = 5 hides the ground behind it, rays to the far ground pass under what
    floats. A crown (x 7.5-9, y 1-2, 3.3 m up) is wide and goes. One crown cube at its corner, at
    (9.5, 0.5), beside the trunk (x 9, y 0): two columns around it within one layer of it (the
    trunk's top and the crown), too few for a wide bottom, and the trunk is grounded: thin. With
    remove_rims it has a removed cube beside it and no more grounded columns than removed ones: the
    crown's rim, removed. Beside a post two columns wide (x 9-9.5, a sign's post under its arm) the
    same cube has more grounded columns around it than removed ones, and stays."""
    ground = np.vstack([ground_patch(1, 5, -5, 5), ground_patch(14, 20, -5, 5)])
    curb = np.vstack([vertical_face(5.0, -5, 5, -1.7, -1.4), slab(5, 5.5, -5, 5, -1.4)])
    trunk = vertical_face(9.0, -0.2, 0.2, -1.4, 1.5, step=0.1)
    crown = slab(7.5, 9.25, 1.0, 2.0, 1.6)
    rim = np.array([[9.5, 0.5, 1.6]])
    for posts, rim_reason in (([trunk], RIM), ([trunk, vertical_face(9.5, -0.2, 0.2, -1.4, 1.5, 0.1)], THIN)):
        points = np.vstack([ground, curb, *posts, crown, rim])
        for rims, expected in ((True, rim_reason), (False, THIN)):
            params = tc.CollapseParams(edge=0.5, sigma=4, method="shadow_aware", remove_rims=rims)
            result = tc.collapse_overhangs(points, params=params)
            check_against_naive(result, points, 4, rims=rims)
            assert (reasons_of_points(result, crown) == FREE_BELOW).all()
            assert (reasons_of_points(result, np.vstack(posts)) == SUPPORTED).all()
            assert reasons_of_points(result, rim)[0] == expected, (len(posts), rims)
            assert result.overhang[-1] == (expected == RIM)


def test_a_trunks_top_removed_above_a_bush_makes_no_rim_of_the_trunk_beside_it():
    """σ = 4; the curb at x = 5 hides the ground behind it, rays to the far ground pass under what
    floats. A bush at x = 8 (grounded) and, 2.6 m above it, the top of a trunk (x 8-8.5, 1.9-2 m up,
    its middle unseen): over the bush the top goes by [CBC]'s own case (above a kept chain), a
    removal never judged wide. Beside it, at x = 8.5, the rest of the top floats over nothing and is
    thin. It is no rim: only removals of wide chains (and of rims) make rims, so a trunk's top is
    not carried off by the paper's case."""
    ground = np.vstack([ground_patch(1, 5, -5, 5), ground_patch(14, 20, -5, 5)])
    curb = np.vstack([vertical_face(5.0, -5, 5, -1.7, -1.4), slab(5, 5.5, -5, 5, -1.4)])
    bush = vertical_face(8.0, -0.2, 0.2, -1.6, -0.6, step=0.1)
    top_over_bush = vertical_face(8.0, -0.2, 0.2, 1.9, 2.1, step=0.1)
    top_beside = vertical_face(8.5, -0.2, 0.2, 1.9, 2.1, step=0.1)
    points = np.vstack([ground, curb, bush, top_over_bush, top_beside])
    for rims in (True, False):
        params = tc.CollapseParams(edge=0.5, sigma=4, method="shadow_aware", remove_rims=rims)
        result = tc.collapse_overhangs(points, params=params)
        check_against_naive(result, points, 4, rims=rims)
        assert (reasons_of_points(result, bush) == SUPPORTED).all()
        assert (reasons_of_points(result, top_over_bush) == ABOVE_KEPT).all()
        assert (reasons_of_points(result, top_beside) == THIN).all(), rims
        assert not result.overhang[-len(top_beside) :].any()


def test_tunnel_ceiling_over_a_lit_floor_goes_and_its_walls_stay():
    floor = ground_patch(1, 20, -2, 2)
    walls = np.vstack(
        [
            np.column_stack([np.arange(4, 16, 0.2), np.full(60, side), np.full(60, z)])
            for side in (-2.0, 2.0)
            for z in np.arange(-1.7, 2.3, 0.2)
        ]
    )
    ceiling = slab(4, 16, -2, 2.01, 2.3)
    points = np.vstack([floor, walls, ceiling])
    result = shadow_aware(points)
    check_against_naive(result, points, 4)
    in_wall_column = np.abs(np.abs(ceiling[:, 1]) - 2.0) < 0.3
    assert np.isin(reasons_of_points(result, ceiling[~in_wall_column]), REMOVED).all()
    assert (reasons_of_points(result, np.vstack([floor, walls])) == SUPPORTED).all()
    paper = tc.collapse_overhangs(points, 0.5, 4)
    assert paper.overhang.sum() <= result.overhang.sum()


def test_a_multipath_point_below_the_road_decides_nothing():
    """A single return 6 m under the road: the paper's rule makes it its column's ground and
    removes the road above it; the shadow-aware rule keeps it (below_ground) and the road."""
    road = ground_patch(1, 12, -3, 3)
    ghost = np.array([[6.1, 0.1, -7.7]])
    points = np.vstack([road, ghost])
    paper = tc.collapse_overhangs(points, 0.5, 4)
    assert paper.overhang.sum() > 0  # the road above the ghost
    result = shadow_aware(points)
    check_against_naive(result, points, 4)
    assert not result.overhang.any()
    assert reasons_of_points(result, ghost)[0] == BELOW_GROUND


def test_a_multipath_patch_under_the_road_is_no_ground():
    """Four returns 2.5 m under the road in a 2 x 2 block of columns (a reflection): they pass the
    4-of-9 support test, but the road lies over most of their neighbours, so they are no ground,
    and the road over them and around them stays."""
    road = ground_patch(1, 12, -3, 3)
    ghosts = np.array([[6.0, 0.0, -4.2], [6.5, 0.0, -4.2], [6.0, 0.5, -4.2], [6.5, 0.5, -4.2]])
    points = np.vstack([road, ghosts])
    result = shadow_aware(points)
    check_against_naive(result, points, 4)
    assert not result.overhang.any()
    assert (reasons_of_points(result, ghosts) == BELOW_GROUND).all()
    # the same patch alone (no road over it) is ground
    alone = shadow_aware(np.vstack([ground_patch(5.5, 7.0, -0.5, 1.0, z=-4.2), ghosts]))
    assert (reasons_of_points(alone, ghosts) == SUPPORTED).all()


def test_a_deep_reflection_behind_the_road_is_no_ground():
    """Twelve returns 8 m under the road, 20 m out, in a 2 x 2 block of columns with no return
    around them (a reflection, as on the Ouster scan 000000): they pass the support test, but the
    line of sight to them runs under the road nearer the sensor, so they are no ground, and the
    road that their rays pass under stays. The same returns seen from above (nothing between
    them and the sensor) stay ground."""
    road = ground_patch(1, 24, -4, 4, z=-1.7)
    road = road[(np.abs(road[:, 0] - 20.25) > 1.0) | (np.abs(road[:, 1]) > 1.0)]  # a hole around them
    ghosts = np.array(
        [[20.0 + 0.5 * (k % 2) + 0.05 * (k // 4), -0.5 + 0.5 * (k // 2 % 2), -9.7] for k in range(12)]
    )
    points = np.vstack([road, ghosts])
    result = shadow_aware(points, 2)
    check_against_naive(result, points, 2)
    assert not result.overhang[: len(road)].any()
    assert (reasons_of_points(result, ghosts) == BELOW_GROUND).all()
    params = tc.CollapseParams(edge=0.5, sigma=2, method="shadow_aware", hidden_ground_margin=100.0)
    off = tc.collapse_overhangs(points, params=params)
    check_against_naive(off, points, 2, hidden=100.0)
    assert off.overhang[: len(road)].any()  # without the test the road over them goes
    above = shadow_aware(ghosts, 2, sensor_origin=(20.0, 0.0, -8.0))
    assert (reasons_of_points(above, ghosts) == SUPPORTED).all()


@pytest.mark.parametrize("sigma", [2, 3, 4])
def test_the_ouster_street_over_a_deep_reflection_stays(shared_data, sigma):
    """The Ouster scan 000000 without a crop: nine returns 9.5 m under the street, 22 m out, in a
    row of three columns. Were they ground (3 of 9 columns, without the hidden-ground test), their
    rays would remove 75 street points (z < 0.3 m, the street lies within 0.2 m of z = 0 in that
    scan's frame)."""
    points = shared_data.ouster_xyzi()[:, :3]
    result = tc.collapse_overhangs(points, 0.5, sigma, method="shadow_aware")
    street = points[:, 2] < 0.3
    assert np.count_nonzero(result.overhang & street) == 0
    assert (reasons_of_points(result, points[points[:, 2] < -9.0]) == BELOW_GROUND).all()


@pytest.mark.parametrize("sigma", [3, 4])
def test_crowns_over_the_seen_ground_of_a_forest_plot_go_as_by_the_paper(shared_data, sigma):
    """The TLS pine plot (10 x 10 m, 114k points; the sensor taken at the plot's centre, 1.5 m over
    its lowest point), where the scanner saw the ground under the crowns: shadow_aware removes every
    point the paper's rule removes (measured: all of them, 39 % at σ 3 and 34 % at σ 4), nothing
    within 1 m of the plot's bottom, and leaves no more half-metre cells with a kept point over 2 m
    above the cell's lowest than the paper does (116 and 157 against 123 and 162 of 400). A rule
    that keeps the thin fringes of crowns over a kept chain below fails it (87-89 % of the
    paper's points, 205 such cells at σ 4)."""
    points = np.load(shared_data.path("forest_tls/TreeLS_pine_plot.npz"))["xyz"].astype(np.float64)
    centre = points.mean(axis=0)
    origin = (centre[0], centre[1], points[:, 2].min() + 1.5)
    paper = tc.collapse_overhangs(points, 0.5, sigma).overhang
    aware = tc.collapse_overhangs(points, 0.5, sigma, method="shadow_aware", sensor_origin=origin).overhang
    assert paper.mean() > 0.3
    assert np.count_nonzero(paper & aware) >= 0.995 * np.count_nonzero(paper)
    assert not aware[points[:, 2] < points[:, 2].min() + 1.0].any()
    cell = np.unique(np.floor(points[:, :2] / 0.5).astype(np.int64), axis=0, return_inverse=True)[1].ravel()
    lowest = np.full(cell.max() + 1, np.inf)
    np.minimum.at(lowest, cell, points[:, 2])
    high = points[:, 2] - lowest[cell] > 2.0

    def cells_shown_blocked(removed):
        blocked = np.zeros(len(lowest), bool)
        np.logical_or.at(blocked, cell, high & ~removed)
        return int(blocked.sum())

    assert cells_shown_blocked(aware) <= cells_shown_blocked(paper)


@pytest.mark.parametrize("sigma", [2, 3, 4])
def test_the_bundled_ouster_street_over_a_shallow_reflection_stays(sigma):
    """The bundled 25 m Ouster sample, seen from its sensor (1.8 m above the origin): returns 1.5-2 m
    under the street, 8-12 m behind the sensor, hold the lowest cube of an L of three columns (the
    street lies 4 layers above them in two more). Taken for ground (3 of 9 columns), they would be
    the ground of every column within 5 m, and their rays, which pass under the street, would remove
    162-191 street points at σ 2 and 3; a 2 x 2 block (4 of 9) is needed."""
    points = load_sample_scan()
    street = (points[:, 2] > -0.5) & (points[:, 2] < 0.3)
    origin = (0.0, 0.0, 1.8)
    default = tc.collapse_overhangs(points, 0.5, sigma, method="shadow_aware", sensor_origin=origin)
    assert np.count_nonzero(default.overhang & street) == 0
    three = tc.CollapseParams(
        edge=0.5, sigma=sigma, method="shadow_aware", sensor_origin=origin, ground_support=3
    )
    street_removed_with_three = np.count_nonzero(
        tc.collapse_overhangs(points, params=three).overhang & street
    )
    if sigma < 4:  # with 3 of 9 the street goes (at σ 4 it lies too close above them to float)
        assert street_removed_with_three > 100


def test_empty_and_single_point_clouds():
    empty = shadow_aware(np.zeros((0, 3)))
    assert empty.num_overhang == 0 and len(empty.cube_reasons) == 0
    single = shadow_aware(np.array([[3.0, 4.0, 1.0]]))
    check_against_naive(single, [[3.0, 4.0, 1.0]], 4)
    assert list(single.cube_reasons) == [NO_GROUND]


def test_paper_method_has_no_reasons_and_is_unchanged():
    rng = np.random.default_rng(3)
    points = rng.uniform(-10, 10, (3000, 3))
    default = tc.collapse_overhangs(points, 0.5, 2)
    paper = tc.collapse_overhangs(points, 0.5, 2, method="paper")
    np.testing.assert_array_equal(default.overhang, paper.overhang)
    assert len(paper.cube_reasons) == 0


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_random_scenes_match_the_naive_reference_for_any_thread_count_and_storage(seed):
    rng = np.random.default_rng(seed)
    ground = np.column_stack([rng.uniform(-15, 15, (4000, 2)), rng.normal(-1.7, 0.05, 4000)])
    ground[:, 2] += 0.1 * ground[:, 0]  # a 10 % slope
    blobs = rng.uniform(-15, 15, (12, 3)) * [1, 1, 0.1] + [0, 0, 2.5]
    canopy = np.vstack([b + rng.normal(0, 0.8, (150, 3)) for b in blobs])
    ghosts = np.column_stack([rng.uniform(-15, 15, (20, 2)), rng.uniform(-9, -3, 20)])
    points = np.vstack([ground, canopy, ghosts])
    origin = (0.3, -0.2, 0.1)
    sigma = int(rng.integers(2, 6))
    results = [
        shadow_aware(points, sigma, sensor_origin=origin, storage=storage, num_threads=threads)
        for storage, threads in (("dense", 1), ("sparse", 1), ("dense", 0), ("auto", 2))
    ]
    check_against_naive(results[0], points, sigma, origin)
    for other in results[1:]:
        np.testing.assert_array_equal(other.overhang, results[0].overhang)
        np.testing.assert_array_equal(other.cube_reasons, results[0].cube_reasons)
    assert results[0].overhang.any()


def test_point_reasons_are_the_reasons_of_each_points_cube():
    """tc.point_reasons against this file's own lookup: each point leveled as the core does, its
    cube quantised here and found in occupied_cubes; not_used for the points cropped away or not
    finite. The removed reasons are exactly the overhang mask."""
    rng = np.random.default_rng(21)
    ground = np.column_stack([rng.uniform(-15, 15, (4000, 2)), rng.normal(-1.7, 0.05, 4000)])
    blobs = rng.uniform(-15, 15, (12, 3)) * [1, 1, 0.1] + [0, 0, 2.5]
    canopy = np.vstack([b + rng.normal(0, 0.8, (150, 3)) for b in blobs])
    points = np.vstack([ground, canopy]).astype(np.float32)
    points[5] = np.nan
    transform = tc.leveling_transform(0.03, -0.02)
    crop = ((-12.0, -12.0, -5.0), (12.0, 12.0, 8.0))
    params = tc.CollapseParams(
        edge=0.5, sigma=4, method="shadow_aware", transform=transform, crop=crop, drop_non_finite=True
    )
    result = tc.collapse_overhangs(points, params=params)
    reasons = tc.point_reasons(points, result, params=params)
    assert reasons.dtype == np.uint8 and reasons.shape == (len(points),)
    q = leveled(points, transform)
    with np.errstate(invalid="ignore"):
        used = np.isfinite(q).all(axis=1) & ((q >= crop[0]) & (q <= crop[1])).all(axis=1)
    assert (~used).sum() == result.num_cropped + result.num_dropped_non_finite > 100
    assert (reasons[~used] == int(CubeReason.not_used)).all()
    np.testing.assert_array_equal(reasons[used], reasons_of_points(result, q[used]))
    np.testing.assert_array_equal(np.isin(reasons, REMOVED), result.overhang)
    assert np.isin(reasons, REMOVED).any() and (reasons == SUPPORTED).any()
    np.testing.assert_array_equal(tc.point_reasons(points, result, transform=transform, crop=crop), reasons)

    paper = tc.collapse_overhangs(points, 0.5, 4, transform=transform, crop=crop, drop_non_finite=True)
    with pytest.raises(ValueError, match="cube reasons"):
        tc.point_reasons(points, paper, params=params)
    with pytest.raises(ValueError, match="points given"):
        tc.point_reasons(points[:-1], result, params=params)
    with pytest.raises(ValueError, match="no occupied cube"):  # other points: the ground 2 m up
        tc.point_reasons(points + np.float32([0, 0, 2]), result, params=params)


def test_parameters_reach_the_core_and_match_the_naive_reference():
    rng = np.random.default_rng(9)
    points = np.vstack(
        [
            np.column_stack([rng.uniform(-8, 8, (1500, 2)), rng.normal(-1.7, 0.03, 1500)]),
            np.column_stack([rng.uniform(2, 5, (300, 2)), rng.uniform(1.5, 2.0, 300)]),
        ]
    )
    params = tc.CollapseParams(
        edge=0.4,
        sigma=3,
        method="shadow_aware",
        ground_radius=1.2,
        ground_support=2,
        azimuth_bins=64,
        free_margin=0.0,
        min_bottom_neighbours=5,
        bottom_window=3,
    )
    result = tc.collapse_overhangs(points, params=params)
    reasons = check_against_naive(
        result, points, 3, radius=1.2, support=2, sectors=64, margin=0.0, neighbours=5, window=3
    )
    assert np.isin(reasons, REMOVED).any()


def test_transform_translation_is_the_default_sensor_origin():
    rng = np.random.default_rng(4)
    points = np.column_stack([rng.uniform(-8, 8, (2000, 2)), rng.normal(-1.7, 0.03, 2000)])
    points = np.vstack([points, np.column_stack([rng.uniform(2, 5, (300, 2)), rng.uniform(1.5, 2.0, 300)])])
    transform = tc.leveling_transform(0.05, -0.03)
    transform[:3, 3] = (1.0, -2.0, 0.5)
    moved = tc.collapse_overhangs(points, 0.5, 3, method="shadow_aware", transform=transform)
    explicit = tc.collapse_overhangs(
        points, 0.5, 3, method="shadow_aware", transform=transform, sensor_origin=(1.0, -2.0, 0.5)
    )
    np.testing.assert_array_equal(moved.cube_reasons, explicit.cube_reasons)
    check_against_naive(moved, leveled(points, transform), 3, (1.0, -2.0, 0.5))


def crown_behind_a_hedge():
    """A 1.2 m hedge at x = 8 hides the ground beyond it; a crown 3.3-4.1 m up at x 11-14: no ray
    the sensor saw passes under it."""
    ground = ground_patch(1, 8, -5, 5)
    hedge = np.vstack([vertical_face(8.0, -5, 5, -1.7, -0.5), slab(8, 8.5, -5, 5, -0.5)])
    crown = np.vstack([slab(11, 14, -1.5, 1.5, z) for z in (1.6, 2.4)])
    return np.vstack([ground, hedge]), crown


def beams(elevation_deg, azimuths_deg):
    e, a = np.radians(elevation_deg), np.radians(np.asarray(azimuths_deg, float))
    return np.column_stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.full(a.size, np.sin(e))])


def test_beams_without_a_return_show_the_space_under_a_crown_empty():
    kept, crown = crown_behind_a_hedge()
    points = np.vstack([kept, crown])
    alone = shadow_aware(points)
    check_against_naive(alone, points, 4)
    # Only its near edge goes: the rays to the crown's far side pass under it.
    assert (reasons_of_points(alone, crown) == SHADOWED).mean() > 0.7
    fan = beams(0.0, np.arange(-20, 20.05, 0.1))
    seen = shadow_aware(points, no_returns=fan)
    check_against_naive(seen, points, 4, no_returns=fan)
    crown_reasons = reasons_of_points(seen, crown)  # its far side is over 5 m from any ground
    assert (crown_reasons[crown_reasons != NO_GROUND] == FREE_BELOW).all()
    assert (crown_reasons == FREE_BELOW).mean() > 0.7
    assert not seen.overhang[: len(kept)].any()
    for lower in (beams(-0.5, np.arange(-20, 20.05, 0.1)), fan * 2.0 - [0, 0, 0.02]):  # below the horizon
        np.testing.assert_array_equal(shadow_aware(points, no_returns=lower).overhang, alone.overhang)
    short = tc.CollapseParams(edge=0.5, sigma=4, method="shadow_aware", no_return_range=10.0)
    np.testing.assert_array_equal(
        tc.collapse_overhangs(points, params=short, no_returns=fan).overhang, alone.overhang
    )
    assert not tc.collapse_overhangs(points, 0.5, 4, no_returns=fan).overhang.any()  # the paper's rule


@pytest.mark.parametrize("seed", [0, 1])
def test_random_beams_without_a_return_match_the_naive_reference(seed):
    rng = np.random.default_rng(seed)
    kept, crown = crown_behind_a_hedge()
    blobs = rng.uniform(-12, 12, (8, 3)) * [1, 1, 0.1] + [0, 0, 2.0]
    canopy = np.vstack([b + rng.normal(0, 0.6, (100, 3)) for b in blobs])
    points = np.vstack([kept, crown, canopy, ground_patch(-12, 0, -12, 12, step=0.3)])
    directions = rng.normal(size=(3000, 3)) * [1, 1, 0.15] * rng.uniform(0.5, 3.0, (3000, 1))
    origin = (0.2, -0.1, 0.05)
    reach = float(rng.uniform(5, 25))
    params = tc.CollapseParams(
        edge=0.5, sigma=3, method="shadow_aware", sensor_origin=origin, no_return_range=reach
    )
    result = tc.collapse_overhangs(points, params=params, no_returns=directions)
    reasons = check_against_naive(result, points, 3, origin, no_returns=directions, no_return_range=reach)
    without = check_against_naive(
        tc.collapse_overhangs(points, 0.5, 3, method="shadow_aware", sensor_origin=origin), points, 3, origin
    )
    assert np.isin(reasons, REMOVED).sum() > np.isin(without, REMOVED).sum()


def test_beams_without_a_return_are_leveled_with_the_points():
    kept, crown = crown_behind_a_hedge()
    points = np.vstack([kept, crown])
    points += np.random.default_rng(0).normal(0.0, 0.01, points.shape)  # none on a cube's face
    transform = tc.leveling_transform(0.06, -0.04)
    rotation = transform[:3, :3]
    fan = beams(0.3, np.arange(-20, 20.05, 0.1))  # not level: rotated back, a level one may dip by 1e-17
    # The scene as a sensor rolled and pitched by the inverse of `transform` sees it.
    result = tc.collapse_overhangs(
        points @ rotation, 0.5, 4, method="shadow_aware", transform=transform, no_returns=fan @ rotation
    )
    check_against_naive(result, leveled(points @ rotation, transform), 4, no_returns=fan)
    assert (reasons_of_points(result, points[len(kept) :]) == FREE_BELOW).mean() > 0.7


@pytest.mark.parametrize(
    ("no_returns", "message"),
    [
        (np.zeros((2, 3)), "no_return_directions row 0"),
        ([[1.0, 0.0, 0.0], [np.nan, 0.0, 0.0]], "no_return_directions row 1"),
        (np.ones((4, 2)), r"\(M, 3\)"),
        (np.ones(3), r"\(M, 3\)"),
    ],
)
def test_bad_beams_without_a_return_raise_value_errors(no_returns, message):
    with pytest.raises(ValueError, match=message):
        shadow_aware(np.zeros((4, 3)), no_returns=no_returns)


@pytest.mark.parametrize(
    ("field", "value", "message"),
    [
        ("method", "magic", "method must be one of"),
        ("ground_radius", -1.0, "ground_radius_m"),
        ("ground_radius", float("nan"), "ground_radius_m"),
        ("ground_support", 0, "ground_support"),
        ("ground_support", 10, "ground_support"),
        ("azimuth_bins", 0, "azimuth_bins"),
        ("free_margin", -0.1, "free_margin_m"),
        ("min_bottom_neighbours", 25, "min_bottom_neighbours"),
        ("sensor_origin", (0.0, float("inf"), 0.0), "sensor_origin"),
        ("sensor_origin", (0.0, 1.0), "sensor_origin"),
        ("no_return_range", 0.0, "no_return_range_m"),
        ("no_return_range", float("inf"), "no_return_range_m"),
    ],
)
def test_bad_parameters_raise_value_errors_naming_them(field, value, message):
    params = tc.CollapseParams(**{"method": "shadow_aware", field: value})
    with pytest.raises(ValueError, match=message):
        tc.collapse_overhangs(np.zeros((4, 3)), params=params)


def test_reason_names_are_documented():
    assert [CubeReason(i).name for i in range(8)] == [
        "supported",
        "below_ground",
        "no_ground_estimate",
        "shadowed",
        "removed_above_kept",
        "removed_free_below",
        "thin",
        "removed_rim",
    ]
    assert tc._core.cube_reason_name(5) == "removed_free_below"


def test_cli_collapse_method_shadow_aware_writes_the_same_mask(tmp_path):
    from terracube.cli import app
    from typer.testing import CliRunner

    ground = ground_patch(1, 5, -5, 5)
    far = ground_patch(14, 20, -5, 5, step=0.1)
    crown = np.vstack([slab(7.75, 10.25, -1.25, 1.25, z) for z in (1.6, 2.4)])
    points = np.vstack([ground, far, crown]).astype(np.float32)
    np.save(tmp_path / "scan.npy", points)
    out = tmp_path / "out"
    args = ["collapse", str(tmp_path / "scan.npy"), "-o", str(out), "-e", "0.5", "-s", "4", "-f", "npz"]
    result = CliRunner().invoke(app, [*args, "--method", "shadow_aware"])
    assert result.exit_code == 0, result.output
    saved = np.load(out / "scan_classified.npz")["overhang"]
    expected = tc.collapse_overhangs(points, 0.5, 4, method="shadow_aware").overhang
    np.testing.assert_array_equal(saved, expected)
    assert expected.sum() > 100 and not tc.collapse_overhangs(points, 0.5, 4).overhang.any()
    # The report counts the cubes by the reason they were kept or removed.
    reasons = tc.collapse_overhangs(points, 0.5, 4, method="shadow_aware").cube_reasons
    counts = np.bincount(reasons, minlength=7)
    assert counts[5] > 0
    line = next(line for line in result.output.splitlines() if "cubes by reason" in line)
    assert f"removed_free_below {counts[5]:,}" in line and f"supported {counts[0]:,}" in line
    assert "cubes by reason" not in CliRunner().invoke(app, args).output  # the paper's rule has none


def test_cli_dem_method_shadow_aware_leaves_the_crown_out_of_the_map(tmp_path):
    from terracube.cli import app
    from typer.testing import CliRunner

    ground = ground_patch(1, 5, -5, 5)
    far = ground_patch(14, 20, -5, 5, step=0.1)
    crown = np.vstack([slab(7.75, 10.25, -1.25, 1.25, z) for z in (1.6, 2.4)])
    np.save(tmp_path / "scan.npy", np.vstack([ground, far, crown]).astype(np.float32))
    maps = {}
    for method in ("paper", "shadow_aware"):
        args = ["dem", str(tmp_path / "scan.npy"), "-o", str(tmp_path / method), "-e", "0.5", "-s", "4"]
        result = CliRunner().invoke(app, [*args, "-r", "0.5", "--method", method, "--no-png"])
        assert result.exit_code == 0, result.output
        maps[method] = tc.ElevationMap.load(tmp_path / method / "scan_dem.npz")
    crown_cells = {method: m.geometry.index_of(9.0, 0.0) for method, m in maps.items()}
    assert maps["paper"]["max"][crown_cells["paper"]] > 2.0  # the paper's rule keeps the crown
    assert np.isnan(maps["shadow_aware"]["max"][crown_cells["shadow_aware"]])  # no ground seen there


def test_simulated_trees_behind_curbs_and_a_tunnel_precision_recall_and_structures_kept():
    """A ray-cast scan (OS1-64-like, sensor 1.73 m up, tilted 3°/-4° and leveled first): trees at
    8-26 m behind 0.3 m curbs, a tunnel with a lit floor, a wall behind a parked van. Measured:
    precision 1.000, recall 0.96 (the paper's rule: 0.51), no wall, trunk or tunnel-wall point removed."""
    from terracube import simulation as sim

    label = sim.Label
    parts = []
    for k, distance in enumerate((8.0, 14.0, 20.0, 26.0)):
        parts += tree_behind(sim, distance, 25.0 + 25.0 * k, "curb")
    for side in (-3.2, 3.2):
        parts.append(sim.Primitive.box((-16.0, side, 2.0), (6.0, 0.2, 2.0), 0.0, label.TUNNEL_WALL))
    parts.append(sim.Primitive.box((-16.0, 0.0, 4.2), (6.0, 3.4, 0.2), 0.0, label.TUNNEL_CEILING))
    parts.append(sim.Primitive.box((6.0, -14.0, 1.5), (4.0, 0.15, 1.5), 0.0, label.WALL))
    parts.append(sim.Primitive.box((6.0, -11.5, 1.0), (2.5, 1.0, 1.0), 0.0, label.BUILDING))
    world = sim.make_scene(parts, 0.0)
    roll, pitch = np.radians(3.0), np.radians(-4.0)
    pose = np.eye(4)
    pose[:3, :3] = tc.leveling_transform(roll, pitch)[:3, :3]
    pose[2, 3] = 1.73
    scan = sim.cast_scan(world, pose, sim.RotatingLidar(), seed=1)
    level = tc.leveling_transform(roll, pitch)
    truth = np.isin(scan.labels, list(sim.OVERHANG_LABELS))
    structures = np.isin(scan.labels, (label.WALL, label.TRUNK, label.TUNNEL_WALL))
    result = tc.collapse_overhangs(scan.points, 0.5, 4, transform=level, method="shadow_aware")
    paper = tc.collapse_overhangs(scan.points, 0.5, 4, transform=level).overhang
    removed = result.overhang
    precision = (removed & truth).sum() / removed.sum()
    recall = (removed & truth).sum() / truth.sum()
    paper_recall = (paper & truth).sum() / truth.sum()
    print(f"precision {precision:.3f} recall {recall:.3f} paper recall {paper_recall:.3f}")
    assert truth.sum() > 2000 and structures.sum() > 2000
    assert precision >= 0.98
    assert recall >= 0.92
    assert (removed & truth).sum() >= 1.5 * (paper & truth).sum()
    assert (removed & structures).sum() <= 0.005 * structures.sum()


# ------------------------------------------------------------------- beams of an organised scan


def organised_simulated_scan(model, world, pose, seed=2):
    """A simulated scan as an organised (channels, steps, 3) image with (0, 0, 0) for no return,
    and the true directions of its empty pixels (row-major), both in the sensor frame."""
    from terracube import simulation as sim

    scan = sim.cast_scan(world, pose, model, seed=seed)
    image = sim.organised_image(scan, model)
    rays = sim.sensor_rays(model)  # firing order: the channels of one step, step by step
    directions = rays.reshape(model.steps_per_revolution, model.channels, 3).transpose(1, 0, 2)
    returned = np.zeros(len(rays), bool)
    returned[scan.ray_indices] = True
    empty = ~returned.reshape(model.steps_per_revolution, model.channels).T
    # Independently: ray r is channel r % channels of step r // channels.
    channel, step = scan.ray_indices % model.channels, scan.ray_indices // model.channels
    np.testing.assert_array_equal(image[channel, step], scan.points)
    assert ((image != 0).any(axis=2) == ~empty).all()
    return image, directions[empty], scan


def tree_behind(sim, distance, azimuth_deg, obstacle):
    """A tree (trunk to 3.6 m, crown 3.2-6 m, 4.4 m across) `distance` m out at `azimuth_deg`, and
    3 m in front of it a 0.3 m curb (`obstacle="curb"`) or a 1.2 m hedge."""
    azimuth = np.radians(azimuth_deg)
    direction = np.array([np.cos(azimuth), np.sin(azimuth)])
    x, y = distance * direction
    front = (distance - 3.0) * direction
    if obstacle == "curb":
        block = sim.Primitive.box((*front, 0.15), (0.15, 3.0, 0.15), float(azimuth), sim.Label.WALL)
    else:
        block = sim.Primitive.box((*front, 0.6), (0.3, 2.5, 0.6), float(azimuth), sim.Label.WALL)
    return [
        sim.Primitive.cylinder(x, y, 0.2, -0.5, 3.6, sim.Label.TRUNK),
        sim.Primitive.ellipsoid((x, y, 4.6), (2.2, 2.2, 1.4), sim.Label.CANOPY),
        block,
    ]


def angle_deg(a, b) -> np.ndarray:
    cosine = (a * b).sum(axis=1) / np.linalg.norm(a, axis=1) / np.linalg.norm(b, axis=1)
    return np.degrees(np.arccos(np.clip(cosine, -1.0, 1.0)))


def test_no_return_directions_of_a_simulated_scan_are_its_empty_beams():
    from terracube import simulation as sim

    world = sim.make_scene([sim.Primitive.box((12.0, 0.0, 3.0), (2.0, 6.0, 0.5), 0.0, sim.Label.BRIDGE_DECK)])
    pose = np.eye(4)
    pose[:3, :3] = tc.leveling_transform(0.03, -0.05)[:3, :3]
    pose[2, 3] = 1.7
    model = sim.RotatingLidar(channels=32, steps_per_revolution=900, max_range=40.0)
    image, truth, _ = organised_simulated_scan(model, world, pose)
    assert 0.3 < len(truth) / (image.shape[0] * image.shape[1]) < 0.7  # the sky and the far ground
    found = tc.no_return_directions(image)
    assert found.shape == truth.shape
    np.testing.assert_allclose(np.linalg.norm(found, axis=1), 1.0)
    assert angle_deg(found, truth).max() < 0.01  # the noise is along the beams only


def test_no_return_directions_of_the_ouster_recording_predict_hidden_returns(shared_data):
    """A real OS1-64 scan (ROS 1 recording, organised column by column): a tenth of its returns
    hidden, the directions found for them from the rest match the returns' own within 0.05 deg."""
    pytest.importorskip("rosbags")
    pytest.importorskip("mcap")
    from terracube.bag import read_bag

    path = shared_data.path("rosbags/ouster_os1_pointcloudset_ros1.mcap")
    cloud = next(read_bag(path, "/os1_cloud_node/points", keep_invalid=True).clouds())
    np.testing.assert_array_equal(cloud.fields["ring"][:64], np.arange(64))  # a column, beam by beam
    image = cloud.points.astype(np.float64).reshape(2048, 64, 3).transpose(1, 0, 2)
    returned = (image != 0).any(axis=2)
    hidden = returned & (np.random.default_rng(1).random(returned.shape) < 0.1)
    shown = np.where(hidden[..., None], 0.0, image)
    found = tc.no_return_directions(shown)
    empty = ~(returned & ~hidden)
    assert len(found) == empty.sum()
    error = angle_deg(found[hidden[empty]], image[hidden])
    assert np.median(error) < 0.01 and np.percentile(error, 99) < 0.05, np.percentile(error, [50, 99])
    # The cloud's own rows with their ring field lay out the same image.
    rows = shown.transpose(1, 0, 2).reshape(-1, 3)
    np.testing.assert_array_equal(tc.no_return_directions(rows, ring=cloud.fields["ring"]), found)
    # Seen from 1.5 m under the sensor the same directions need the sensor's position.
    lifted = np.where((shown != 0).any(axis=2)[..., None], shown + [0.0, 0.0, 1.5], 0.0)
    np.testing.assert_allclose(tc.no_return_directions(lifted, origin=(0.0, 0.0, 1.5)), found, atol=1e-9)


def test_no_return_directions_bad_and_edge_inputs():
    with pytest.raises(ValueError, match=r"\(H, W, 3\)"):
        tc.no_return_directions(np.zeros((10, 3)))
    with pytest.raises(ValueError, match="same number of pixels"):
        tc.no_return_directions(np.ones((5, 3)), ring=np.array([0, 0, 1, 1, 1]))
    with pytest.raises(ValueError, match=r"ring \(N,\)"):
        tc.no_return_directions(np.ones((5, 3)), ring=np.zeros(4, int))
    with pytest.raises(ValueError, match="whole beam numbers"):
        tc.no_return_directions(np.ones((4, 3)), ring=np.zeros(4))
    with pytest.raises(ValueError, match="origin"):
        tc.no_return_directions(np.ones((2, 2, 3)), origin=(0.0, np.nan, 0.0))
    with pytest.raises(ValueError, match="no return"):
        tc.no_return_directions(np.full((4, 8, 3), np.nan))
    full = np.ones((4, 8, 3))
    assert tc.no_return_directions(full).shape == (0, 3)
    # A beam without any return takes the elevation of the line through the others.
    a = np.radians(np.arange(8) * 45.0)
    image = np.stack(
        [np.column_stack([np.cos(a), np.sin(a), np.full(8, np.tan(e))]) for e in (-0.2, -0.1, 0.0, 0.1)]
    )
    image[2] = np.nan
    found = tc.no_return_directions(image)
    expected = np.column_stack([np.cos(a), np.sin(a), np.zeros(8)])
    assert angle_deg(found, expected).max() < 1e-6


def test_no_returns_of_the_simulated_scene_raise_recall_not_removed_structure():
    """A VLP-32-like scan behind 1.2 m hedges: the beams that returned nothing pass under crowns
    no ray to a point passes under."""
    from terracube import simulation as sim

    label = sim.Label
    parts = []
    for k, distance in enumerate((12.0, 18.0, 24.0)):
        parts += tree_behind(sim, distance, 30.0 + 40.0 * k, "hedge")
    world = sim.make_scene(parts, 0.0)
    pose = np.eye(4)
    pose[2, 3] = 1.73
    model = sim.RotatingLidar(
        channels=32, vertical_fov_min=-25.0, vertical_fov_max=15.0, steps_per_revolution=1800, max_range=80.0
    )
    image, beams_truth, scan = organised_simulated_scan(model, world, pose, seed=3)
    truth = np.isin(scan.labels, list(sim.OVERHANG_LABELS))
    structures = np.isin(scan.labels, (label.WALL, label.TRUNK))
    without = tc.collapse_overhangs(scan.points, 0.5, 4, method="shadow_aware").overhang
    params = tc.CollapseParams(edge=0.5, sigma=4, method="shadow_aware", no_return_range=80.0)
    found = tc.no_return_directions(image)
    assert angle_deg(found, beams_truth).max() < 0.01
    with_beams = tc.collapse_overhangs(scan.points, params=params, no_returns=found).overhang
    recall = [(removed & truth).sum() / truth.sum() for removed in (without, with_beams)]
    print(f"canopy recall without / with the beams: {recall[0]:.3f} / {recall[1]:.3f}")
    assert recall[1] >= recall[0] + 0.05
    assert (with_beams & truth).sum() / with_beams.sum() >= 0.98
    assert not (with_beams & structures).any()


def test_organised_image_refuses_another_scanner_or_sensor():
    from terracube import simulation as sim

    world = sim.make_scene([], 0.0)
    pose = np.eye(4)
    pose[2, 3] = 1.7
    small = sim.RotatingLidar(channels=16, steps_per_revolution=360)
    scan = sim.cast_scan(world, pose, sim.RotatingLidar(channels=32, steps_per_revolution=720))
    with pytest.raises(ValueError, match="exceed this sensor's 5760 rays"):
        sim.organised_image(scan, small)
    with pytest.raises(ValueError, match="RotatingLidar"):
        sim.organised_image(scan, sim.Tilting2DScanner())


def hedge_scene_image():
    """The VLP-32-like scan of three trees behind 1.2 m hedges as an organised image, its returns
    (row order of the image) and the labels of those returns."""
    from terracube import simulation as sim

    parts = []
    for k, distance in enumerate((12.0, 18.0, 24.0)):
        parts += tree_behind(sim, distance, 30.0 + 40.0 * k, "hedge")
    pose = np.eye(4)
    pose[2, 3] = 1.73
    model = sim.RotatingLidar(
        channels=32, vertical_fov_min=-25.0, vertical_fov_max=15.0, steps_per_revolution=1800, max_range=80.0
    )
    scan = sim.cast_scan(sim.make_scene(parts, 0.0), pose, model, seed=3)
    image = sim.organised_image(scan, model)
    labels = np.full(model.channels * model.steps_per_revolution, -1)  # pixel (channel, step), row-major
    ray = scan.ray_indices  # channel ray % channels of step ray // channels
    labels[(ray % model.channels) * model.steps_per_revolution + ray // model.channels] = scan.labels
    return image, labels


def test_empty_beams_of_a_ring_field_and_when_there_are_none():
    from terracube.pipeline import empty_beams

    image, _ = hedge_scene_image()
    xyz = image.reshape(-1, 3).astype(np.float32)
    ring = np.repeat(np.arange(32, dtype=np.uint16), 1800)
    # Column-major, as the OS1-64 recording: the beams interleave, each beam's pixels in order.
    found = empty_beams(
        image.transpose(1, 0, 2).reshape(-1, 3), np.tile(np.arange(32, dtype=np.uint16), 1800)
    )
    expected = tc.no_return_directions(image)
    assert len(found) == len(expected) == np.count_nonzero(~(xyz != 0).any(axis=1)) > 1000
    np.testing.assert_allclose(np.sort(found, axis=0), np.sort(expected, axis=0), atol=1e-9)
    returned = (xyz != 0).any(axis=1)
    assert empty_beams(xyz, None) is None
    assert empty_beams(xyz[returned], ring[returned]) is None  # a driver that drops them: unequal rings
    assert empty_beams(xyz, ring.astype(np.float32)) is None  # not an integer field
    assert len(empty_beams(xyz[-3600:], ring[-3600:])) > 1800  # the top two beams: mostly sky
    full = np.where(returned[:, None], xyz, 5.0)
    assert empty_beams(full, ring) is None  # no empty pixel


def test_cli_stages_read_the_empty_pixels_of_an_organised_file_as_beams(tmp_path):
    """A scan file with a ring field (an Ouster driver's PCD) gives the shadow-aware stages its
    empty pixels: the same mask as collapse_overhangs given no_return_directions, more canopy out of
    the DEM than the returns alone, and nothing changes for the paper's rule."""
    from terracube import simulation as sim
    from terracube.cli import app
    from terracube.io import write_pcd
    from typer.testing import CliRunner

    image, labels = hedge_scene_image()
    xyz = image.reshape(-1, 3).astype(np.float32)
    ring = np.repeat(np.arange(32, dtype=np.uint16), 1800)
    returned = (xyz != 0).any(axis=1)
    write_pcd(tmp_path / "organised.pcd", {"xyz": xyz, "ring": ring})
    np.save(tmp_path / "returns.npy", xyz[returned])
    canopy = labels[returned] == sim.Label.CANOPY
    structures = np.isin(labels[returned], (sim.Label.WALL, sim.Label.TRUNK))
    runner = CliRunner()
    common = ["-e", "0.5", "-s", "4", "--method", "shadow_aware"]

    result = runner.invoke(
        app, ["collapse", str(tmp_path / "organised.pcd"), "-o", str(tmp_path), "-f", "npz", *common]
    )
    assert result.exit_code == 0, result.output
    beams = tc.no_return_directions(image)
    assert f"{len(beams):,} beams without a return showed free space" in result.output
    saved = np.load(tmp_path / "organised_classified.npz")["overhang"].astype(bool)
    params = tc.CollapseParams(edge=0.5, sigma=4, method="shadow_aware")  # no_return_range: the config's 30 m
    expected = tc.collapse_overhangs(xyz[returned], params=params, no_returns=beams).overhang
    assert not saved[~returned].any()
    np.testing.assert_array_equal(saved[returned], expected)
    alone = tc.collapse_overhangs(xyz[returned], params=params).overhang
    assert (expected & canopy).sum() >= (alone & canopy).sum() + 0.05 * canopy.sum()
    assert not (expected & structures).any()
    assert f"picture: {tmp_path / 'organised_reasons.png'}" in result.output  # why each point went

    high = {}
    for name in ("organised.pcd", "returns.npy"):
        out = tmp_path / name.split(".")[0]
        result = runner.invoke(
            app, ["dem", str(tmp_path / name), "-o", str(out), "-r", "0.5", "--no-png", *common]
        )
        assert result.exit_code == 0, result.output
        assert ("beams without a return" in result.output) == (name == "organised.pcd")
        dem = tc.ElevationMap.load(out / f"{name.split('.')[0]}_dem.npz")["max"]
        high[name] = np.count_nonzero(dem > 1.0)  # crown cells left in the map (sensor frame: ground -1.73)
    assert high["organised.pcd"] < 0.8 * high["returns.npy"]
    pictures = runner.invoke(
        app, ["dem", str(tmp_path / "organised.pcd"), "-o", str(tmp_path / "png"), *common]
    )
    assert pictures.exit_code == 0, pictures.output
    # why the DEM lost its crowns
    assert (tmp_path / "png" / "organised_reasons.png").is_file(), pictures.output
    for stage in ("classify", "fem"):  # their overhang removal takes them too
        args = [stage, str(tmp_path / "organised.pcd"), "-o", str(tmp_path / stage), "-r", "0.5", "--no-png"]
        result = runner.invoke(app, [*args, "--remove-overhangs", *common])
        assert result.exit_code == 0, result.output
        assert f"{len(beams):,} beams without a return" in result.output
        assert "beams without a return" not in runner.invoke(app, [*args, "--keep-overhangs", *common]).output
    # dem_without_overhangs takes the same beams
    _, removed = tc.dem_without_overhangs(xyz[returned], collapse=params, no_returns=beams)
    np.testing.assert_array_equal(removed.overhang, expected)
    paper = runner.invoke(
        app, ["collapse", str(tmp_path / "organised.pcd"), "-o", str(tmp_path / "p"), "-f", "npz"]
    )
    assert paper.exit_code == 0 and "beams without a return" not in paper.output
    assert (tmp_path / "p" / "organised_overhangs.png").is_file()
    assert not (tmp_path / "p" / "organised_reasons.png").exists()  # the paper's rule has no reasons


def test_batch_and_run_stage_take_the_beams_of_an_organised_file(tmp_path):
    from terracube.batch import process_file
    from terracube.config import default_config
    from terracube.io import read_cloud, write_pcd
    from terracube.pipeline import read_stage_input, run_stage

    image, _ = hedge_scene_image()
    xyz = image.reshape(-1, 3).astype(np.float32)
    write_pcd(
        tmp_path / "organised.pcd", {"xyz": xyz, "ring": np.repeat(np.arange(32, dtype=np.uint16), 1800)}
    )
    config = default_config().replace("collapse", edge=0.5, sigma=4, method="shadow_aware")
    points, beams = read_stage_input(tmp_path / "organised.pcd", config)
    np.testing.assert_array_equal(points, xyz)
    assert len(beams) == len(tc.no_return_directions(image))
    assert read_stage_input(tmp_path / "organised.pcd", default_config())[1] is None  # the paper's rule
    # A file whose origin is not the sensor's (the sensor at q): with the sensor origin given (in
    # the leveled frame, R q), the beams are the sensor's own.
    q = np.array([0.3, -0.2, 0.5])
    shifted = np.where((xyz != 0).any(axis=1, keepdims=True), xyz + q, 0.0).astype(np.float32)
    write_pcd(
        tmp_path / "shifted.pcd", {"xyz": shifted, "ring": np.repeat(np.arange(32, dtype=np.uint16), 1800)}
    )
    tilted = config.replace("frame", roll_deg=3.0)
    moved = tilted.replace("collapse", sensor_origin=tuple(tilted.frame.transform()[:3, :3] @ q))
    found = read_stage_input(tmp_path / "shifted.pcd", moved)[1]
    assert len(found) == len(beams) and angle_deg(found, beams).max() < 1e-3
    assert angle_deg(read_stage_input(tmp_path / "shifted.pcd", tilted)[1], beams).max() > 0.1  # seen from 0
    record = process_file("collapse", tmp_path / "organised.pcd", tmp_path / "batch", config, {"png": False})
    assert record.status == "ok", record.error
    assert any(f"{len(beams):,} beams without a return" in line for line in record.lines)
    run_stage("collapse", points, "direct", tmp_path / "direct", config, no_returns=beams, png=False)
    batch = read_cloud(tmp_path / "batch" / "organised_classified.ply")["label"]
    direct = read_cloud(tmp_path / "direct" / "direct_classified.ply")["label"]
    returned = (xyz != 0).any(axis=1)
    params = tc.CollapseParams(edge=0.5, sigma=4, method="shadow_aware")
    expected = tc.collapse_overhangs(xyz[returned], params=params, no_returns=beams).overhang
    np.testing.assert_array_equal(batch, direct)
    np.testing.assert_array_equal(batch[returned], expected)


def test_stream_on_a_folder_of_organised_files_uses_their_beams(tmp_path):
    """``terracube stream FOLDER --method shadow_aware`` on scans with a ring field: each update gets
    the file's returns and its empty pixels, as LocalMap.update given them does."""
    from terracube.cli import app, stream_params
    from terracube.io import write_pcd
    from terracube.poses import write_tum_poses
    from typer.testing import CliRunner

    image, _ = hedge_scene_image()
    xyz = image.reshape(-1, 3).astype(np.float32)
    returned = (xyz != 0).any(axis=1)
    scans = tmp_path / "scans"
    scans.mkdir()
    for k in range(2):
        write_pcd(
            scans / f"{k:06d}.pcd", {"xyz": xyz, "ring": np.repeat(np.arange(32, dtype=np.uint16), 1800)}
        )
    poses = [np.eye(4), np.eye(4)]
    for k, pose in enumerate(poses):
        pose[:3, 3] = (0.5 * k, 0.0, 1.73)
    write_tum_poses(tmp_path / "tum.txt", [0.0, 0.1], poses)
    options = ["--poses", str(tmp_path / "tum.txt"), "--length", "40", "--resolution", "0.5", "--no-png"]
    options += ["--robot-height", "2"]
    result = CliRunner().invoke(
        app, ["stream", str(scans), "-o", str(tmp_path / "s"), "--method", "shadow_aware", *options]
    )
    assert result.exit_code == 0, result.output
    beams = tc.no_return_directions(image)
    assert f"{2 * len(beams):,} beams without a return" in result.output
    params = stream_params(
        dict(length=40.0, resolution=0.5, collapse_method="shadow_aware", robot_height=2.0)
    )
    expected = tc.LocalMap(params=params)
    for stamp, pose in zip((0.0, 0.1), poses, strict=True):
        expected.update(xyz[returned], pose, stamp, no_returns=beams)
    written = tc.ElevationMap.load(tmp_path / "s" / "local_map.npz")
    np.testing.assert_array_equal(written["elevation"], expected.to_elevation_map()["elevation"])
    alone = tc.LocalMap(params=params)
    for stamp, pose in zip((0.0, 0.1), poses, strict=True):
        alone.update(xyz[returned], pose, stamp)
    crowns = [np.count_nonzero(m["elevation"] > 1.0) for m in (written, alone.to_elevation_map())]
    print("cells over 1 m with / without the beams:", crowns)
    assert crowns[0] < 0.5 * crowns[1]  # the beams keep crowns behind the hedges out of the map


def _organised_pcd(path, xyz, ring, height, width):
    """A PCD of ``xyz`` and ``ring`` whose header says HEIGHT x WIDTH (written unorganised, then the
    header's two lines changed, as an Ouster driver's organised file reads)."""
    from terracube.io import write_pcd

    write_pcd(path, {"xyz": xyz, "ring": ring})
    data = path.read_bytes()
    old = f"WIDTH {len(xyz)}\nHEIGHT 1\n".encode()
    assert data.count(old) == 1
    path.write_bytes(data.replace(old, f"WIDTH {width}\nHEIGHT {height}\n".encode()))


def test_an_organised_pcd_gives_its_empty_pixels_by_its_image_layout_though_its_ring_field_is_zero_there(
    tmp_path,
):
    """An Ouster organised PCD writes ring 0 in its empty pixels, so its rings count unequally: the
    HEIGHT x WIDTH layout of its header lays the image out instead (the CLI used no beams, silently)."""
    from terracube.cli import app
    from typer.testing import CliRunner

    image, _ = hedge_scene_image()
    xyz = image.reshape(-1, 3).astype(np.float32)
    returned = (xyz != 0).any(axis=1)
    ring = np.where(returned, np.repeat(np.arange(32, dtype=np.uint16), 1800), 0).astype(np.uint16)
    _organised_pcd(tmp_path / "organised.pcd", xyz, ring, 32, 1800)
    runner = CliRunner()
    common = ["-f", "npz", "--no-png", "-e", "0.5", "-s", "4", "--method", "shadow_aware"]
    result = runner.invoke(app, ["collapse", str(tmp_path / "organised.pcd"), "-o", str(tmp_path), *common])
    assert result.exit_code == 0, result.output
    beams = tc.no_return_directions(image)
    assert f"{len(beams):,} beams without a return showed free space" in result.output
    params = tc.CollapseParams(edge=0.5, sigma=4, method="shadow_aware")
    expected = tc.collapse_overhangs(xyz[returned], params=params, no_returns=beams).overhang
    saved = np.load(tmp_path / "organised_classified.npz")["overhang"]
    np.testing.assert_array_equal(saved[returned], expected)

    # The same rows unorganised (HEIGHT 1): the ring field cannot lay them out, and the note says why.
    _organised_pcd(tmp_path / "flat.pcd", xyz, ring, 1, len(xyz))
    result = runner.invoke(app, ["collapse", str(tmp_path / "flat.pcd"), "-o", str(tmp_path), *common])
    assert result.exit_code == 0, result.output
    assert "beams without a return" not in result.output
    counts = np.bincount(ring)
    assert (
        "note: shadow_aware took no empty pixels as free space: the cloud is not organised "
        f"(no HEIGHT > 1 with WIDTH x HEIGHT = its points) and its ring field gives the beams unequal "
        f"pixel counts ({counts.min():,}..{counts.max():,}" in result.output
    )
    np.save(tmp_path / "returns.npy", xyz[returned])
    result = runner.invoke(
        app, ["dem", str(tmp_path / "returns.npy"), "-o", str(tmp_path), "--no-png", *common[3:]]
    )
    assert result.exit_code == 0, result.output
    assert (
        "free space: the cloud is not organised (no HEIGHT > 1 with WIDTH x HEIGHT = its points) "
        "and has no ring field" in result.output
    )
    paper = runner.invoke(
        app, ["collapse", str(tmp_path / "flat.pcd"), "-o", str(tmp_path / "p"), *common[:-2]]
    )
    assert paper.exit_code == 0 and "shadow_aware" not in paper.output


def test_the_real_organised_ouster_pcd_gives_the_empty_pixels_of_its_128_x_1875_image(shared_data):
    from terracube.config import default_config
    from terracube.io import organised_shape, read_cloud
    from terracube.pipeline import read_stage_input

    path = shared_data.path("ouster128/ouster128_000000.pcd")
    assert organised_shape(path) == (128, 1875)  # the header's HEIGHT, WIDTH
    xyz = read_cloud(path)["xyz"]
    config = default_config().replace("collapse", method="shadow_aware")
    points, beams = read_stage_input(path, config)
    expected = tc.no_return_directions(xyz.reshape(128, 1875, 3))
    assert len(expected) == np.count_nonzero(~(xyz != 0).any(axis=1)) == 34102
    np.testing.assert_allclose(beams, expected, atol=1e-12)
