"""Ground-truth boxes and camera geometry on synthetic label and depth images (no GL)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from genesis_rl.sim.interface import CameraConfig
from genesis_rl.sim.lite.render.gt_boxes import MAX_BOX_RANGE, MIN_BOX_PIXELS, SILHOUETTE_FILL, ground_truth_boxes
from genesis_rl.sim.lite.render.view import camera_axes, camera_pose, outside_view

CAM = CameraConfig(320, 240)  # 90 degrees: focal length 160 px
CPOS = np.array([0.0, 0.0, 1.5])
SEDAN = (4.5, 1.8, 1.5)
LABEL = 40


def _frame(rects: list[tuple[int, int, int, int, int, float]]) -> tuple[np.ndarray, np.ndarray]:
    """Labels and depth images with (label, x0, y0, x1, y1, depth) rectangles painted in order."""
    labels = np.zeros((CAM.height, CAM.width), np.uint8)
    depth = np.full((CAM.height, CAM.width), 1000.0, np.float32)
    for lab, x0, y0, x1, y1, d in rects:
        labels[y0:y1, x0:x1] = lab
        depth[y0:y1, x0:x1] = d
    return labels, depth


def _boxes(xy: tuple[float, float], labels: np.ndarray, depth: np.ndarray, yaw: float = 0.0):
    poses = np.array([[0.0, 0.0, 0.0, 0.0, 0.0], [xy[0], xy[1], 0.0, yaw, 0.0]])
    dims = np.array([SEDAN, SEDAN])
    return ground_truth_boxes(CAM, 0.3, poses, dims, [1], [LABEL], CPOS, 0.0, 0.0, labels, depth)


def test_projected_box_of_a_car_ahead() -> None:
    """A sedan 20 m ahead: its rear face (17.75 m) spans 16 px by 13.5 px below the horizon; the box is the
    extent of its label's pixels, the distance their nearest depth, fully visible."""
    rear = 20.0 - SEDAN[0] / 2
    half_w = CAM.focal_px * SEDAN[1] / 2 / rear  # 8.1 px
    below = CAM.focal_px * 1.5 / rear  # 13.5 px: the camera is at roof height
    x0, x1 = round(160 - half_w), round(160 + half_w)
    labels, depth = _frame([(LABEL, x0, 120, x1, round(120 + below), rear), (LABEL + 1, 0, 0, 320, 40, 5.0)])
    (b,) = _boxes((20.0, 0.0), labels, depth)
    assert (b.vehicle_id, b.x0, b.y0, b.x1, b.y1) == (1, x0, 120, x1, round(120 + below))
    assert b.distance == pytest.approx(rear) and not b.truncated
    assert b.visible_fraction == 1.0


def test_occlusion_lowers_the_visible_fraction() -> None:
    """Half the silhouette hidden: the box shrinks to the visible half and visible_fraction is about
    0.5 / SILHOUETTE_FILL; under MIN_BOX_PIXELS visible pixels, no box."""
    labels, depth = _frame([(LABEL, 152, 120, 168, 133, 17.75), (LABEL + 1, 160, 100, 200, 140, 9.0)])
    (b,) = _boxes((20.0, 0.0), labels, depth)
    assert (b.x0, b.x1) == (152, 160)
    assert b.visible_fraction == pytest.approx(0.5 / SILHOUETTE_FILL, rel=0.15)
    labels, depth = _frame([(LABEL, 152, 120, 152 + MIN_BOX_PIXELS - 1, 121, 17.75)])
    assert _boxes((20.0, 0.0), labels, depth) == []


def test_no_box_out_of_range_or_behind() -> None:
    """Label pixels alone make no box: the vehicle must be within MAX_BOX_RANGE and in front of the camera."""
    labels, depth = _frame([(LABEL, 150, 110, 170, 130, 10.0)])
    assert _boxes((MAX_BOX_RANGE + 5.0, 0.0), labels, depth) == []
    assert _boxes((-20.0, 0.0), labels, depth) == []
    assert len(_boxes((MAX_BOX_RANGE - 5.0, 0.0), labels, depth)) == 1


def test_truncated_at_the_border_and_beside_the_camera() -> None:
    """A car cut by the image's left edge, and one partly behind the camera, are truncated; the latter's
    box reaches the border it crosses."""
    labels, depth = _frame([(LABEL, 0, 110, 40, 140, 6.0)])
    (b,) = _boxes((8.0, 7.0), labels, depth)  # 45 degrees left: straddles the left edge
    assert b.truncated and b.x0 == 0
    (b,) = _boxes((0.5, 2.5), labels, depth)  # beside the ego, half of it behind the camera plane
    assert b.truncated and b.x0 == 0


def test_camera_pose_and_axes() -> None:
    """The camera sits mount_x ahead and mount_z above the ego's origin along its heading, pitched by
    pitch_deg; its axes are forward, right and up."""
    cam = CameraConfig(320, 240, mount_x=0.8, mount_z=1.5, pitch_deg=-5.0)
    pos, yaw, pitch = camera_pose(np.array([10.0, 20.0, 3.0, math.pi / 2, 0.0]), cam)
    assert np.allclose(pos, [10.0, 20.8, 4.5]) and yaw == math.pi / 2
    assert pitch == pytest.approx(math.radians(-5.0))
    fwd, right, up = camera_axes(math.pi / 2, 0.0)
    assert np.allclose(fwd, [0, 1, 0]) and np.allclose(right, [1, 0, 0]) and np.allclose(up, [0, 0, 1])


def test_outside_view() -> None:
    """Behind the camera or beyond a side plane of the 90-degree frustum (sphere and shadow included)."""
    poses = np.array([[20.0, 0, 0, 0, 0], [-20.0, 0, 0, 0, 0], [3.0, 20.0, 0, 0, 0], [15.0, 12.0, 0, 0, 0],
                      [-2.0, 0, 0, 0, 0]])
    dims = np.tile(SEDAN, (5, 1))
    hidden = outside_view(poses, dims, 90.0, CPOS, 0.0, 0.0, 0.0)
    assert hidden.tolist() == [False, True, True, False, False]  # the last one is within its own radius
    assert not outside_view(poses, dims, 90.0, CPOS, 0.0, 0.0, 30.0)[2]  # a long shadow may reach the view
