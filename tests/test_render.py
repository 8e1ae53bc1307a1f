"""Headless mesh rendering: frame shape and content, response to poses (moving, identical, out of view), placement
of body-frame vertices (an offset mesh against a centred one at the equivalent pose, which catches MuJoCo's
mesh re-centring) and GIF output.

Objects are told apart by hue: the three meshes are red, green and blue, the background is grey-black.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh
from PIL import Image

from cfd_torch.envs.render import MeshRenderer, write_gif
from cfd_torch.rotation import rotation_matrix

WIDTH, HEIGHT = 160, 120
COLORS = [(0.85, 0.15, 0.15, 1.0), (0.15, 0.7, 0.15, 1.0), (0.15, 0.3, 0.85, 1.0)]
POSES = np.array(
    [
        [0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
        [0.5, 0.1, 0.05, 0.2, -0.1, 0.6],
        [-0.2, 0.5, 0.1, 0.0, 0.0, 0.0],
    ]
)


def _pixels(img: np.ndarray, channel: int) -> int:
    """Number of pixels whose ``channel`` (0 red, 1 green, 2 blue) exceeds both others by 40 levels."""
    img = img.astype(np.int32)
    others = [c for c in range(3) if c != channel]
    return int(
        (
            (img[..., channel] > img[..., others[0]] + 40) & (img[..., channel] > img[..., others[1]] + 40)
        ).sum()
    )


@pytest.fixture(scope="module")
def renderer():
    """Two boxes (red, green) and a sphere (blue), framed automatically at the first render's poses."""
    box_a = trimesh.creation.box((0.4, 0.3, 0.2))
    box_b = trimesh.creation.box((0.2, 0.2, 0.3))
    ball = trimesh.creation.icosphere(2, radius=0.15)
    meshes = [(m.vertices, m.faces) for m in (box_a, box_b, ball)]
    r = MeshRenderer(meshes, COLORS, width=WIDTH, height=HEIGHT)
    r.render(POSES)  # fixes the camera
    yield r
    r.close()


def test_frame_shape_dtype_and_content(renderer):
    img = renderer.render(POSES)
    assert img.shape == (HEIGHT, WIDTH, 3) and img.dtype == np.uint8
    counts = [_pixels(img, c) for c in range(3)]
    assert min(counts) > 100, counts  # all three objects visible
    assert len(np.unique(img.reshape(-1, 3), axis=0)) > 20  # shaded, not flat
    assert (img.max(axis=2) > 40).mean() < 0.9  # background remains


def test_identical_poses_give_identical_fresh_frames(renderer):
    a = renderer.render(POSES)
    moved = POSES.copy()
    moved[0, 0] += 0.3
    renderer.render(moved)
    b = renderer.render(torch.tensor(POSES, requires_grad=True))
    assert np.array_equal(a, b)
    assert not np.shares_memory(a, b)


def test_moving_one_object_changes_the_frame(renderer):
    a = renderer.render(POSES)
    moved = POSES.copy()
    moved[2, :3] += [0.1, -0.1, 0.05]
    moved[0, 5] += 0.5
    b = renderer.render(moved)
    diff = np.abs(a.astype(np.int32) - b.astype(np.int32)).max(axis=2)
    assert (diff > 30).sum() > 200


def test_object_moved_out_of_view_disappears(renderer):
    before = _pixels(renderer.render(POSES), 1)
    away = POSES.copy()
    away[1, :3] += [100.0, 0.0, 0.0]
    img = renderer.render(away)
    assert before > 100 and _pixels(img, 1) == 0
    assert _pixels(img, 0) > 100 and _pixels(img, 2) > 100


def test_body_frame_vertices_are_drawn_where_the_pose_maps_them():
    # An elongated box rotated in its body frame and shifted off the origin (MuJoCo re-centres and re-orients it
    # at compile time) against the same box centred, posed so that both occupy the same world points:
    # R (v + c) + t = R v + (R c + t).
    box = trimesh.creation.box((0.5, 0.2, 0.1))
    box.apply_transform(trimesh.transformations.rotation_matrix(0.7, [1.0, 2.0, 3.0]))
    c = np.array([0.25, -0.1, 0.15])
    pose = np.array([0.1, 0.2, 0.3, 0.3, -0.5, 0.8])
    R = rotation_matrix(torch.tensor(pose[3:])).numpy()
    centred_pose = np.concatenate([R @ c + pose[:3], pose[3:]])
    far = np.array([0.0, 0.0, -100.0, 0.0, 0.0, 0.0])
    meshes = [(box.vertices + c, box.faces), (box.vertices, box.faces)]
    camera = dict(lookat=(0.3, 0.1, 0.3), distance=1.5, azimuth=60.0, elevation=-35.0)
    r = MeshRenderer(meshes, [COLORS[0]] * 2, width=WIDTH, height=HEIGHT, camera=camera)
    try:
        offset = r.render(np.stack([pose, far]))
        centred = r.render(np.stack([far, centred_pose]))
    finally:
        r.close()
    r.close()  # idempotent
    covered = _pixels(offset, 0)
    assert covered > 500
    mismatch = (np.abs(offset.astype(np.int32) - centred.astype(np.int32)).max(axis=2) > 30).sum()
    assert mismatch <= 0.01 * covered


def test_invalid_inputs_are_refused(renderer):
    with pytest.raises(ValueError, match="poses"):
        renderer.render(POSES[:2])
    with pytest.raises(ValueError, match="camera"):
        MeshRenderer([(np.eye(4, 3), [[0, 1, 2]])], camera=dict(fov=30))


def test_write_gif(tmp_path, renderer):
    frames = []
    for k in range(5):
        poses = POSES.copy()
        poses[2, 0] += 0.05 * k
        frames.append(renderer.render(poses))
    path = write_gif(frames, tmp_path / "sub" / "clip.gif", fps=10)
    with Image.open(path) as gif:
        assert gif.n_frames == len(frames)
        assert gif.size == (WIDTH, HEIGHT)
        assert gif.info["duration"] == 100


def test_per_frame_colors_override_and_restore(renderer):
    plain = renderer.render(POSES)
    swapped = renderer.render(POSES, colors=[COLORS[2], COLORS[0], COLORS[1]])  # red box drawn blue, ...
    assert _pixels(swapped, 2) > 100 and _pixels(swapped, 0) > 100
    assert np.abs(swapped.astype(int) - plain.astype(int)).sum(2).astype(bool).sum() > 100
    assert np.array_equal(renderer.render(POSES), plain)  # a frame without colors uses the construction ones
    with pytest.raises(ValueError, match="colors must be an \\(3, 4\\) array"):
        renderer.render(POSES, colors=COLORS[:2])
    with pytest.raises(ValueError, match="colors must be an \\(3, 4\\) array"):
        renderer.render(POSES, colors=[(2.0, 0.0, 0.0, 1.0)] * 3)
