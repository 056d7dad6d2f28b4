"""``NavMapConfig.unknown_clearance``: the buffer navigable cells keep to unseen space, apart from
the one they keep to obstacles and drops."""

from __future__ import annotations

import numpy as np
import pytest
from image2sim.simulator.navigation import synthetic as syn
from image2sim.simulator.navigation.embodiment import ConfigError, Embodiment, NavMapConfig
from image2sim.simulator.navigation.extract import extract_navmap_from_points

RADIUS = Embodiment().radius
SPACING = 0.04
CELL = NavMapConfig().voxel_size


def floor_beside_a_wall() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A 4 x 3 m floor seen from above with a 2 m wall along x = 0; its other three edges open
    onto unseen space (no points)."""
    floor = syn.plane_patch((0, 0, 0), (4, 0, 0), (0, 3, 0), (0, 0, 1), SPACING)
    wall = syn.plane_patch((0, 0, 0.02), (0, 3, 0), (0, 0, 2.0), (1, 0, 0), SPACING)
    points = np.concatenate((floor[0], wall[0]))
    normals = np.concatenate((floor[1], wall[1]))
    return points, normals, np.array([[2.0, 1.5, 1.25]])


def margins(unknown_clearance: float | None) -> tuple[float, float, np.ndarray]:
    """(distance of the navigable cells to the wall, to the nearest open edge, the map's clearance)."""
    points, normals, cams = floor_beside_a_wall()
    m = extract_navmap_from_points(
        points, normals, camera_positions=cams, config=NavMapConfig(unknown_clearance=unknown_clearance)
    )
    xy = m.points[:, :2]
    to_open = np.minimum.reduce([4.0 - xy[:, 0], xy[:, 1], 3.0 - xy[:, 1]])
    return float(xy[:, 0].min()), float(to_open.min()), m.clearance[m.navigable]


def test_none_keeps_the_safety_buffer_to_unseen_space():
    to_wall, to_open, clearance = margins(None)
    assert to_wall >= RADIUS - 1e-9 and to_wall < RADIUS + 2 * CELL
    assert to_open >= RADIUS - CELL / 2 - 1e-9 and to_open < RADIUS + 2 * CELL
    assert (clearance >= RADIUS - 1e-9).all()


def test_the_default_is_the_papers_rule():
    # Since 2026-11-28 only obstacles and drops project the buffer by default (None: the old rule).
    assert NavMapConfig().unknown_clearance == 0.0


@pytest.mark.parametrize("unknown", [0.0, 0.05])
def test_a_smaller_unknown_clearance_reaches_nearer_unseen_space_but_not_obstacles(unknown):
    to_wall, to_open, clearance = margins(unknown)
    # The wall is an obstacle: the buffer there is unchanged.
    assert to_wall >= RADIUS - 1e-9 and to_wall < RADIUS + 2 * CELL
    # Unseen space: cells come as near as the smaller buffer allows (cell centres, half a cell out).
    assert unknown - 1e-9 <= to_open < unknown + CELL + 1e-9
    # Clearance counts unseen space as standing the difference farther out: every navigable cell
    # still reads at least the safety buffer, so the graph's safety cost treats it alike.
    assert (clearance >= RADIUS - 1e-9).all()


def test_drops_keep_the_safety_buffer_whatever_the_unknown_clearance():
    """Beside the stairs the upper storey ends at a drop onto the seen lower floor: a drop is not
    unseen space, so its buffer stays the safety buffer."""
    w = syn.two_levels_with_stairs(spacing=SPACING)
    m = extract_navmap_from_points(
        w.points, w.normals, camera_positions=w.camera_positions, config=NavMapConfig(unknown_clearance=0.0)
    )
    upper = m.points[m.points[:, 2] > 1.1]
    x_s = 4.0 - 8 * 0.3 / 2
    beside = upper[(upper[:, 1] > 1.2 + RADIUS + 0.05)]
    assert beside[:, 0].min() >= x_s + RADIUS - 0.05 - 1e-9


def test_unknown_clearance_is_validated_and_capped_by_the_safety_buffer():
    with pytest.raises(ConfigError, match="unknown_clearance"):
        NavMapConfig(unknown_clearance=-0.1)
    points, normals, cams = floor_beside_a_wall()
    loose = extract_navmap_from_points(
        points, normals, camera_positions=cams, config=NavMapConfig(unknown_clearance=1.0)
    )
    buffer = extract_navmap_from_points(
        points, normals, camera_positions=cams, config=NavMapConfig(unknown_clearance=None)
    )
    assert loose.unknown_clearance == pytest.approx(RADIUS)
    np.testing.assert_array_equal(loose.navigable, buffer.navigable)
