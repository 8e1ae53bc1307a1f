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
    with pytest.raises(TypeError, match="poses must be an array of real numbers"):
        renderer.render(POSES.astype(np.complex128))
    with pytest.raises(ValueError, match="camera"):
        MeshRenderer([(np.eye(4, 3), [[0, 1, 2]])], camera=dict(fov=30))
    box = trimesh.creation.box((0.4, 0.3, 0.2))
    mesh = [(box.vertices, box.faces)]
    bad = {
        "camera\\['distance'\\] must be a finite number > 0": dict(camera=dict(distance=-1.0)),
        "camera\\['distance'\\]": dict(camera=dict(distance=float("nan"))),
        "camera\\['lookat'\\] must be a finite \\(3,\\) point": dict(camera=dict(lookat=(0.0, 0.0))),
        "camera\\['azimuth'\\]": dict(camera=dict(azimuth="north")),
        "width must be a positive int": dict(width=64.5),
        "height must be a positive int": dict(height=True),
        "colors must be RGBA values in \\[0, 1\\]; row 0": dict(colors=[(float("nan"), 0.0, 0.0, 1.0)]),
        "floor must be a finite height": dict(floor=float("nan")),
    }
    for match, kwargs in bad.items():
        with pytest.raises(ValueError, match=match):
            MeshRenderer(mesh, **kwargs)
    with pytest.raises(ValueError, match="meshes\\[0\\] faces must hold whole numbers"):
        MeshRenderer([(box.vertices, box.faces + 0.5)])


def test_a_camera_moved_to_an_invalid_setting_is_refused_at_the_next_render():
    """(A distance <= 0 reached MuJoCo, which printed an error and ended the process.)"""
    box = trimesh.creation.box((0.4, 0.3, 0.2))
    r = MeshRenderer([(box.vertices, box.faces)], width=32, height=24)
    try:
        assert r.render(np.zeros((1, 6))).max() > 0
        r.camera.distance = 0.0
        with pytest.raises(ValueError, match="self.camera\\['distance'\\] must be a finite number > 0"):
            r.render(np.zeros((1, 6)))
    finally:
        r.close()


def test_a_given_lookat_is_framed_about_itself():
    """With only ``lookat`` given, the distance is chosen so that every mesh is in view about that point."""
    box = trimesh.creation.box((0.4, 0.3, 0.2))
    r = MeshRenderer(
        [(box.vertices, box.faces)],
        [(0.15, 0.7, 0.15, 1.0)],
        width=64,
        height=48,
        camera={"lookat": (3.0, 0.0, 0.0)},
    )
    try:
        img = r.render(np.zeros((1, 6)))
        assert _pixels(img, 1) > 0  # the box, 3 m from where the camera looks, is in the picture
        assert tuple(r.camera.lookat) == (3.0, 0.0, 0.0)
    finally:
        r.close()


def _inside(mask: np.ndarray) -> bool:
    """Some pixels set, none on the frame's edge."""
    return bool(mask.any()) and not (mask[0].any() or mask[-1].any() or mask[:, 0].any() or mask[:, -1].any())


def _colour_mask(img: np.ndarray, channel: int) -> np.ndarray:
    img = img.astype(np.int32)
    a, b = (c for c in range(3) if c != channel)
    return (img[..., channel] > img[..., a] + 40) & (img[..., channel] > img[..., b] + 40)


@pytest.mark.parametrize(
    "size", [(100, 200), (200, 100), (150, 150)], ids=["portrait", "landscape", "square"]
)
def test_automatic_framing_and_task_cameras_hold_everything_in_any_image_shape(size):
    """The automatic framing (two boxes 4 m apart across the view) and a task's camera (Push: its green target
    disc, drawn anywhere in its angle range) keep everything inside the frame, portrait images included (the
    cameras were sized from the vertical field of view only: in a 1:2 portrait frame a box and Push's target fell
    outside)."""
    from cfd_torch.envs import make_core
    from cfd_torch.envs.core import task_at

    W, H = size
    box = trimesh.creation.box((0.2, 0.2, 0.2))
    r = MeshRenderer([(box.vertices, box.faces)] * 2, [COLORS[0], COLORS[2]], width=W, height=H)
    try:
        img = r.render(np.array([[-2.0, 0, 0, 0, 0, 0], [2.0, 0, 0, 0, 0, 0]]))
        assert _inside(_colour_mask(img, 0)) and _inside(_colour_mask(img, 2))
    finally:
        r.close()
    core = make_core("cfd_torch/Push-v0", angle_range=1.5)
    r = core.renderer(W, H)
    try:
        state = core.reset(seed=[0, 1, 2, 3], batch_size=4)
        target = state.task["target"]
        assert float(target[:, 1].abs().max()) > 1.0  # targets drawn far to the sides
        for b in range(4):
            img = core.draw(r, state.q[b], task_at(state, b))
            assert _inside(_colour_mask(img, 1)), (size, b)
    finally:
        r.close()


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


def test_gif_delays_are_what_browsers_play(tmp_path):
    """GIF delays are whole hundredths of a second and browsers play delays under 20 ms as 100 ms: at 100 fps every
    second frame is kept, 20 ms each (the clip's duration kept), the last frame included."""
    frames = [np.full((8, 8, 3), 20 * k, dtype=np.uint8) for k in range(7)]
    with Image.open(write_gif(frames, tmp_path / "fast.gif", fps=100.0)) as gif:
        assert gif.n_frames == 4  # frames 0, 2, 4, 6
        durations = []
        for k in range(gif.n_frames):
            gif.seek(k)
            durations.append(gif.info["duration"])
            assert int(np.asarray(gif.convert("RGB"))[0, 0, 0]) == frames[min(2 * k, 6)][0, 0, 0]
        assert durations == [20] * 4
    with Image.open(write_gif(frames, tmp_path / "sixty.gif", fps=60.0)) as gif:
        assert gif.n_frames == 4 and gif.info["duration"] == 30  # 2 / 60 s, to the nearest 10 ms
    with pytest.raises(ValueError, match="path must end in .gif"):
        write_gif(frames, tmp_path / "clip.png")
    with pytest.raises(ValueError, match="fps must be a finite number > 0"):
        write_gif(frames, tmp_path / "clip.gif", fps=float("nan"))
    with pytest.raises(ValueError, match="fps must be at least"):
        write_gif(frames, tmp_path / "clip.gif", fps=1e-3)
    with pytest.raises(TypeError, match="frames\\[0\\] must be a NumPy array"):
        write_gif([torch.zeros(8, 8, 3, dtype=torch.uint8)], tmp_path / "clip.gif")


def test_per_frame_colors_override_and_restore(renderer):
    plain = renderer.render(POSES)
    swapped = renderer.render(POSES, colors=[COLORS[2], COLORS[0], COLORS[1]])  # red box drawn blue, ...
    assert _pixels(swapped, 2) > 100 and _pixels(swapped, 0) > 100
    assert np.abs(swapped.astype(int) - plain.astype(int)).sum(2).astype(bool).sum() > 100
    assert np.array_equal(renderer.render(POSES), plain)  # a frame without colors uses the construction ones
    with pytest.raises(ValueError, match="colors must be an \\(3, 4\\) array"):
        renderer.render(POSES, colors=COLORS[:2])
    with pytest.raises(ValueError, match="colors must be RGBA values in \\[0, 1\\]; row 0"):
        renderer.render(POSES, colors=[(2.0, 0.0, 0.0, 1.0)] * 3)


def _project(camera, point, width: int, height: int, fovy: float = 45.0) -> tuple[float, float]:
    """Pixel (column, row) of world ``point`` [m] through a free MuJoCo camera (its azimuth, elevation, lookat and
    distance; MuJoCo's 45 degree vertical field of view): an independent pinhole model, y up in the world, rows down
    in the image."""
    az, el = np.radians(camera.azimuth), np.radians(camera.elevation)
    forward = np.array([np.cos(az) * np.cos(el), np.sin(az) * np.cos(el), np.sin(el)])
    eye = np.asarray(camera.lookat, dtype=np.float64) - camera.distance * forward
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    d = np.asarray(point, dtype=np.float64) - eye
    f = 0.5 * height / np.tan(np.radians(0.5 * fovy))
    return 0.5 * width + f * (d @ right) / (d @ forward), 0.5 * height - f * (d @ up) / (d @ forward)


@pytest.mark.parametrize("azimuth, elevation", [(90.0, -45.0), (270.0, -60.0), (30.0, -20.0)])
def test_bodies_are_drawn_where_the_camera_projects_them(azimuth, elevation):
    """A small box's pixels are centred where a pinhole model of the camera puts its centre, for moves along x, y
    and z: the frame is neither mirrored nor upside down (frames that were flipped left-right or top-bottom passed
    every other test here)."""
    box = trimesh.creation.box((0.06, 0.06, 0.06))
    W, H = 200, 150
    camera = dict(lookat=(0.0, 0.0, 0.0), distance=2.0, azimuth=azimuth, elevation=elevation)
    r = MeshRenderer([(box.vertices, box.faces)], [COLORS[0]], width=W, height=H, camera=camera)
    try:
        for centre in ([0.0, 0.0, 0.0], [0.4, 0.0, 0.0], [0.0, 0.4, 0.0], [0.0, 0.0, 0.3], [-0.3, 0.2, 0.1]):
            img = r.render(np.array([[*centre, 0.0, 0.0, 0.0]]))
            rows, cols = np.nonzero(_colour_mask(img, 0))
            u, v = _project(r.camera, centre, W, H)
            # pixel k covers [k, k + 1): its centre is k + 0.5
            assert abs(cols.mean() + 0.5 - u) < 1.5 and abs(rows.mean() + 0.5 - v) < 1.5, (centre, u, v)
    finally:
        r.close()


def _pixel(img: np.ndarray, uv: tuple[float, float]) -> np.ndarray:
    return img[int(uv[1]), int(uv[0])].astype(np.int32)


def test_billiards_draws_the_object_ball_black():
    """The task's object ball (``task["target"]``) is the dark one, whichever it is (drawing another ball black
    passed the suite)."""
    from cfd_torch.envs import make_core
    from cfd_torch.envs.core import task_at

    core = make_core("cfd_torch/Billiards-v0")
    r = core.renderer(320, 320)
    try:
        for seed in range(3):
            state = core.reset(seed, 1)
            task = task_at(state, 0)
            img = core.draw(r, state.q[0], task)
            brightest = [int(_pixel(img, _project(r.camera, p, 320, 320)).max()) for p in state.q[0, :16, :3]]
            k = int(task["target"])
            others = brightest[:k] + brightest[k + 1 :]
            # observed 54-60 against >= 201
            assert brightest[k] < 90 and min(others) > 150, (seed, k, brightest)
    finally:
        r.close()


def test_sort_draws_each_cube_and_region_in_its_class_colour():
    """Each cube is drawn in its class's colour (red 0, yellow 1) and region k, at ``task["centres"][k]``, in class
    k's (cubes drawn in the other class's colour passed the suite)."""
    from cfd_torch.envs import make_core
    from cfd_torch.envs.core import task_at

    def hue(px: np.ndarray) -> int | None:
        r_, g, b = px
        if r_ - g > 60 and g - b < 40:
            return 0  # red
        if g - b > 60 and r_ - b > 60:
            return 1  # yellow
        return None

    core = make_core("cfd_torch/Sort-v0")
    r = core.renderer(320, 320)
    try:
        for seed in range(3):
            state = core.reset(seed, 1)
            task = task_at(state, 0)
            img = core.draw(r, state.q[0], task)
            for i in range(core.num_cubes):
                top = state.q[0, i, :3].numpy() + [0.0, 0.0, 0.5 * core.cube_size]
                drawn = hue(_pixel(img, _project(r.camera, top, 320, 320)))
                assert drawn == int(task["classes"][i]), (seed, i)
            for k in range(2):
                centre = [*task["centres"][k].tolist(), 0.0]
                assert hue(_pixel(img, _project(r.camera, centre, 320, 320))) == k, (seed, k)
    finally:
        r.close()


def test_write_gif_keeps_the_last_frame(tmp_path):
    """At 100 fps every second frame is kept and the last one: six frames give frames 0, 2, 4 and 5."""
    frames = [np.full((8, 8, 3), 30 * k, dtype=np.uint8) for k in range(6)]
    with Image.open(write_gif(frames, tmp_path / "even.gif", fps=100.0)) as gif:
        shown = []
        for k in range(gif.n_frames):
            gif.seek(k)
            shown.append(int(np.asarray(gif.convert("RGB"))[0, 0, 0]))
    assert shown == [0, 60, 120, 150]


def _make_renderer_in_child(queue) -> None:
    box = trimesh.creation.box()
    try:
        MeshRenderer([(box.vertices, box.faces)], width=32, height=32).close()
        queue.put("made")
    except RuntimeError as err:
        queue.put(str(err))


def test_a_process_forked_after_an_egl_context_refuses_to_render():
    """A child forked from a process that made an EGL context hangs in its first EGL call (gymnasium's
    AsyncVectorEnv forks its workers by default): it refuses to make a renderer instead, naming the fix."""
    import multiprocessing

    from cfd_torch.envs import render

    box = trimesh.creation.box()
    MeshRenderer([(box.vertices, box.faces)], width=32, height=32).close()  # this process has made a context
    if not render._egl_backend():
        pytest.skip("the OpenGL backend is not EGL")
    queue = multiprocessing.get_context("fork").Queue()
    child = multiprocessing.get_context("fork").Process(target=_make_renderer_in_child, args=(queue,))
    child.start()
    child.join(60)
    if child.is_alive():
        child.kill()
        pytest.fail("the forked child hung making a renderer")
    message = queue.get(timeout=5)
    assert "forked from one that had made an EGL context" in message and "{'context': 'spawn'}" in message


@pytest.mark.parametrize("task", ["Billiards", "Push", "Sort", "Gather", "AntPush"])
def test_every_task_is_drawn_with_x_to_the_right_and_y_away(task):
    """The same view of the world in every task: +x to the right, +y up the image (away from the viewer), so that
    an action along +x moves a pusher right in every task's frames (Sort and Gather were drawn turned 180 deg)."""
    from cfd_torch.envs import make_core

    core = make_core(f"cfd_torch/{task}-v0")
    r = core.renderer(200, 200)
    try:
        lookat = np.asarray(r.camera.lookat)
        u0, v0 = _project(r.camera, lookat, 200, 200)
        ux, vx = _project(r.camera, lookat + [0.2, 0.0, 0.0], 200, 200)
        uy, vy = _project(r.camera, lookat + [0.0, 0.2, 0.0], 200, 200)
        assert ux - u0 > 5 and abs(vx - v0) < 1  # right, level
        assert v0 - vy > 2 and abs(uy - u0) < 1  # up the image
    finally:
        r.close()


def test_render_without_a_render_mode_warns_and_from_another_thread_is_refused():
    """Gymnasium's conventions: render() on an environment made without a render mode warns and returns None;
    an environment's renderer draws on the thread that made it, and another thread gets a clear error (EGL's own
    is EGL_BAD_ACCESS from eglMakeCurrent)."""
    import threading

    import gymnasium as gym

    env = gym.make("cfd_torch/Push-v0").unwrapped
    env.reset(seed=0)
    with pytest.warns(UserWarning, match="without specifying any render mode"):
        assert env.render() is None
    env = gym.make("cfd_torch/Push-v0", render_mode="rgb_array", width=48, height=48).unwrapped
    env.reset(seed=0)
    assert env.render().shape == (48, 48, 3)
    errors: list[BaseException] = []

    def other() -> None:
        try:
            env.render()
        except RuntimeError as err:
            errors.append(err)

    thread = threading.Thread(target=other)
    thread.start()
    thread.join()
    assert len(errors) == 1 and "another thread than the one that first rendered" in str(errors[0])
    env.close()


@pytest.mark.parametrize("task", ["Push", "AntPush"])
def test_the_target_is_visible_in_a_small_image(task):
    """The goal of Push and AntPush shows in the small images pixel-observation agents use (64 x 64), in the default
    view and in a wider one (``distance=8``): the success disc alone covered 4 pixels and 0."""
    from cfd_torch.envs import make_core

    def green(img: np.ndarray) -> int:
        i = img.astype(np.int32)
        return int(((i[..., 1] > i[..., 0] + 30) & (i[..., 1] > i[..., 2] + 30)).sum())

    for kwargs in ({}, {"distance": 8.0}):
        core = make_core(f"cfd_torch/{task}-v0", **kwargs)
        state = core.reset(0, 1)
        r = core.renderer(64, 64)
        try:
            img = core.draw(r, state.q[0], {k: v[0] for k, v in state.task.items()})
        finally:
            r.close()
        assert green(img) >= 15, (kwargs, green(img))  # observed 21-23
