"""Known object sizes as the metric scale (lift.measure, ``data lift --object-size``): parsing, lifting
both ends from pinhole frames and panorama cube faces of an analytic box room, combining lengths."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from image2sim.simulator.geometry.cameras import EquirectCamera
from image2sim.simulator.lift.measure import (
    ObjectLength,
    ObjectSize,
    measure_object,
    parse_object_size,
    scale_from_lengths,
)
from image2sim.simulator.lift.scale import ScaleError, estimate_metric_frame
from image2sim.simulator.lift.types import DepthEstimate, PinholeView

from tests.simulator.test_lift_planes import PLANES, K, _pose, _render


def _hit(origin: np.ndarray, ray: np.ndarray) -> np.ndarray:
    """Where a world ray from inside the room first meets a wall, the floor or the ceiling."""
    best = np.inf
    for n, d in PLANES:
        denom = ray @ n
        if abs(denom) > 1e-12:
            t = (d - origin @ n) / denom
            if 0 < t < best:
                best = t
    return origin + best * ray


def _in_units(T: np.ndarray, s: float) -> np.ndarray:
    """A metric pose in reconstruction units (metres / s)."""
    U = T.copy()
    U[:3, 3] = T[:3, 3] / s
    return U


def test_parse_object_size_and_its_errors():
    size = parse_object_size(" img_003:120,40:120.5,300=2.0 ")
    assert size == ObjectSize("img_003", (120.0, 40.0), (120.5, 300.0), 2.0)
    assert parse_object_size(size.label()) == size
    for text, message in [
        ("img:1,2:3,4", "expected FRAME:X0,Y0:X1,Y1=METRES"),
        ("img:1,2=1.0", "expected FRAME:X0,Y0:X1,Y1=METRES"),
        ("img:1,2:3,4=-1", "the length must be positive"),
        ("img:1,2:3,4=0", "the length must be positive"),
        ("img:1,2:1,2=1.0", "both ends are the same pixel"),
        ("img:1,2:3,inf=1.0", "every number must be finite"),
    ]:
        with pytest.raises(ValueError, match=message):
            parse_object_size(text)


@pytest.mark.parametrize("s", [1.0, 0.37])
def test_a_pinhole_length_gives_the_scale_in_any_reconstruction_units(s):
    """Ends on the back wall and on the floor of a box room: the lifted length is the true one over
    the reconstruction's scale, so the scale comes back exactly; the uncertainty is the pixel term."""
    T = _pose([0.3, -1.0, 1.5], 10.0)
    depth, _, image = _render(T)
    est = DepthEstimate(depth / s, np.full_like(depth, 0.9))
    a, b = (20.0, 30.0), (70.0, 85.0)  # back wall, floor (away from corners)
    true = np.linalg.norm(
        _hit(T[:3, 3], T[:3, :3] @ np.linalg.solve(K, [a[0] + 0.5, a[1] + 0.5, 1]))
        - _hit(T[:3, 3], T[:3, :3] @ np.linalg.solve(K, [b[0] + 0.5, b[1] + 0.5, 1]))
    )
    size = ObjectSize("f0", a, b, float(true))
    view = PinholeView(image, K, _in_units(T, s))
    got = measure_object(size, K, view.cam_to_world, [(view, est)], float(K[0, 0]))
    assert got.length == pytest.approx(true / s, rel=1e-5)
    assert got.scale == pytest.approx(s, rel=1e-5)
    # One pixel at 64 px focal over a ~2.8 m length at 2-3 m range: about 2 %; nothing from the spread.
    assert 0.005 < got.uncertainty < 0.05


def test_a_panorama_length_is_read_from_the_cube_face_its_pixel_falls_in():
    """An equirect frame's ends are lifted through whichever of its six faces sees them."""
    size_px = 48
    Kf = np.array([[size_px / 2, 0, size_px / 2], [0, size_px / 2, size_px / 2], [0, 0, 1.0]])
    centre = [0.4, 0.2, 1.4]
    faces = [_pose(centre, yaw) for yaw in (0, 90, 180, 270)]
    for pitch in (90, -90):
        T = _pose(centre, 0)
        a = np.radians(pitch)
        T[:3, :3] = T[:3, :3] @ np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
        faces.append(T)
    views = []
    import tests.simulator.test_lift_planes as box

    for T in faces:
        old = box.K, box.H, box.W
        box.K, box.H, box.W = Kf, size_px, size_px
        try:
            depth, _, image = _render(T)
        finally:
            box.K, box.H, box.W = old
        views.append((PinholeView(image, Kf, T), DepthEstimate(depth, np.full_like(depth, 0.9))))
    pano = _pose(centre, 0)
    h, w = 64, 128
    ends = [(5.0, 40.0), (70.0, 20.0)]  # below the horizon at one side, above it at the other
    cam = EquirectCamera(h, w)
    rays = [
        pano[:3, :3]
        @ cam.pixel_to_ray(
            torch.tensor(x + 0.5, dtype=torch.float64), torch.tensor(y + 0.5, dtype=torch.float64)
        ).numpy()
        for x, y in ends
    ]
    true = np.linalg.norm(_hit(np.array(centre), rays[0]) - _hit(np.array(centre), rays[1]))
    got = measure_object(ObjectSize("p0", ends[0], ends[1], float(true)), (h, w), pano, views, size_px / 2)
    # Face pixels are read in windows of +-2 px around the ray's pixel (median of a tilted surface).
    assert got.scale == pytest.approx(1.0, rel=0.005)  # 0.14 %: a window reaching a room corner


def test_an_end_without_confident_depth_is_named():
    T = _pose([0.0, 0.0, 1.5], 0.0)
    depth, _, image = _render(T)
    conf = np.full_like(depth, 0.9)
    conf[:, :40] = 0.1  # the left third is unmatched
    view = PinholeView(image, K, T)
    with pytest.raises(ValueError, match="first end: no confident depth within 8 px"):
        measure_object(
            ObjectSize("f", (5, 40), (100, 40), 1.0), K, T, [(view, DepthEstimate(depth, conf))], 64.0
        )
    got = measure_object(
        ObjectSize("f", (45, 40), (100, 40), 1.0), K, T, [(view, DepthEstimate(depth, conf))], 64.0
    )
    assert got.length > 0  # 45 px: the window reaches confident pixels


def _length(scale: float, uncertainty: float) -> ObjectLength:
    return ObjectLength(ObjectSize("f", (0, 0), (1, 1), scale), 1.0, uncertainty, np.zeros((2, 3)))


def test_lengths_combine_by_their_uncertainties_and_disagreement_widens_it():
    s, u = scale_from_lengths([_length(2.0, 0.01)])
    assert s == pytest.approx(2.0) and u == pytest.approx(0.01)
    s, u = scale_from_lengths([_length(2.0, 0.01), _length(2.02, 0.01)])  # agree within 1 sigma
    assert s == pytest.approx(math.sqrt(2.0 * 2.02)) and u == pytest.approx(0.01 / math.sqrt(2))
    s, _ = scale_from_lengths([_length(2.0, 0.01), _length(3.0, 0.1)])  # the precise one dominates
    assert 2.0 < s < 2.02
    _, u = scale_from_lengths([_length(2.0, 0.01), _length(2.4, 0.01)])  # 18 % apart at 1 % each
    assert u > 0.05
    with pytest.raises(ValueError, match="no object sizes"):
        scale_from_lengths([])


def test_the_metric_frame_takes_its_scale_from_object_lengths():
    from tests.simulator.test_lift_scale import _room

    poses, points = _room(seed=2)
    result = estimate_metric_frame(poses, points, object_lengths=[_length(1.5, 0.01)])
    assert result.method == "object_size" and result.scale == pytest.approx(1.5)
    assert result.uncertainty == pytest.approx(0.01) and result.details["object_sizes"][0]["scale"] == 1.5
    with pytest.raises(ScaleError, match="not both --camera-height and --object-size"):
        estimate_metric_frame(poses, points, camera_height=1.4, object_lengths=[_length(1.5, 0.01)])
