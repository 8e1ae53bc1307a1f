"""Headless RGB frames of rigid bodies from their own triangle meshes and poses (MuJoCo's OpenGL renderer).

One ``MjSpec`` holds a mocap body per rigid body, each carrying its mesh as a visual-only geom; a frame copies the
poses to ``data.mocap_pos``/``mocap_quat``, runs ``mj_kinematics`` and rasterises the scene off-screen.

MuJoCo fixes its OpenGL backend when it is first imported; ``cfd_torch/__init__.py``, which runs before this
module, sets ``MUJOCO_GL=egl`` when it is unset, there is no X display, an EGL library is found and mujoco is not
imported yet. A process that imports mujoco (or pytorch_kinematics, or gymnasium's MuJoCo environments) before
cfd_torch must set it itself.

MuJoCo re-centres every mesh at its centroid and aligns it with its principal axes when it compiles the model,
and compensates by setting the geom's ``pos``/``quat`` to that frame; the geoms here carry no pose of their own,
so the rendered vertices are the body-frame vertices mapped by the body pose (to float32 rounding).
"""

from __future__ import annotations

import atexit
import math
import os
import weakref
from collections.abc import Mapping, Sequence
from pathlib import Path

import mujoco
import numpy as np
import numpy.typing as npt
import torch
from PIL import Image

from cfd_torch._validate import is_int, is_real

from .core import half_view_angle, real_array

__all__ = ["MeshRenderer", "write_gif"]

# Tableau-like colours, cycled when there are more meshes than entries.
_PALETTE = (
    (0.122, 0.467, 0.706, 1.0),
    (1.000, 0.498, 0.055, 1.0),
    (0.173, 0.627, 0.173, 1.0),
    (0.839, 0.153, 0.157, 1.0),
    (0.580, 0.404, 0.741, 1.0),
    (0.549, 0.337, 0.294, 1.0),
    (0.890, 0.467, 0.761, 1.0),
    (0.498, 0.498, 0.498, 1.0),
    (0.737, 0.741, 0.133, 1.0),
    (0.090, 0.745, 0.812, 1.0),
)
_CAMERA_KEYS = ("lookat", "distance", "azimuth", "elevation")
# Default view direction [deg] and margin around the bounding sphere when framing the first render's poses.
_DEFAULT_AZIMUTH = 135.0
_DEFAULT_ELEVATION = -30.0
_FRAME_MARGIN = 1.15

# Renderers still open at interpreter exit are closed by an atexit hook registered after the first OpenGL
# context exists, so that it runs before MuJoCo's own hook terminates the EGL display (atexit runs last-in,
# first-out); freeing a context after that raises EGLError from __del__.
_OPEN: weakref.WeakSet[MeshRenderer] = weakref.WeakSet()
_atexit_registered = False


def _close_open_renderers() -> None:
    for renderer in list(_OPEN):
        renderer.close()


# A process forked from one that has made an EGL context hangs in its own first EGL call (MuJoCo's, through
# libEGL's state copied mid-use): such a child refuses to make a renderer instead (gymnasium's AsyncVectorEnv forks
# its workers by default on Linux before Python 3.14).
_made_egl_context = False
_forked_after_egl_context = False


def _after_fork_in_child() -> None:
    global _forked_after_egl_context
    _forked_after_egl_context = _forked_after_egl_context or _made_egl_context


os.register_at_fork(after_in_child=_after_fork_in_child)


def _egl_backend() -> bool:
    return "egl" in str(getattr(mujoco.gl_context.GLContext, "__module__", "")).lower()


def _numpy(x: npt.ArrayLike | torch.Tensor, name: str, dtype: npt.DTypeLike) -> np.ndarray:
    """``x`` as an array of ``dtype``: real numbers only (:func:`.core.real_array`), and whole numbers for an
    integer ``dtype``."""
    if isinstance(x, torch.Tensor):
        x = x.detach().cpu().numpy()
    try:
        array = real_array(x, name)
    except ValueError as e:
        raise ValueError(f"{name} must be convertible to a {np.dtype(dtype).name} array: {e}") from e
    if np.dtype(dtype).kind in "iu" and not (np.isfinite(array).all() and (array == np.round(array)).all()):
        raise ValueError(f"{name} must hold whole numbers (vertex indices)")
    return array.astype(dtype)


def _check_camera(camera: Mapping[str, object], where: str) -> None:
    """A ValueError naming the key unless ``lookat`` is a finite (3,) point, ``distance`` a finite number > 0 and
    ``azimuth``, ``elevation`` finite numbers [deg] (the keys given)."""
    for key, value in camera.items():
        if key == "lookat":
            try:
                point = np.asarray(value, dtype=np.float64)
            except (TypeError, ValueError):
                point = None
            if point is None or point.shape != (3,) or not np.isfinite(point).all():
                raise ValueError(f"{where}['lookat'] must be a finite (3,) point [m], got {value!r}")
        elif not (is_real(value) and math.isfinite(value)) or (key == "distance" and not value > 0):
            what = "a finite number > 0 [m]" if key == "distance" else "a finite number [deg]"
            raise ValueError(f"{where}[{key!r}] must be {what}, got {value!r}")


def _check_colours(rgba: np.ndarray, n: int, name: str) -> None:
    """A ValueError naming ``name`` unless ``rgba`` is (n, 4) of finite values in [0, 1]."""
    if rgba.shape != (n, 4):
        raise ValueError(f"{name} must be an ({n}, 4) array of RGBA values in [0, 1], got shape {rgba.shape}")
    bad = ~(np.isfinite(rgba) & (rgba >= 0) & (rgba <= 1))
    if bad.any():
        i = int(np.nonzero(bad.any(1))[0][0])
        raise ValueError(f"{name} must be RGBA values in [0, 1]; row {i} is {rgba[i].tolist()}")


def _quaternions(rotvec: np.ndarray) -> np.ndarray:
    """(N, 4) unit quaternions (w, x, y, z) of rotation vectors ``rotvec`` (N, 3) (axis * angle [rad]).

    q = (cos(theta/2), sin(theta/2)/theta * omega); sin(theta/2)/theta = sinc(theta/(2 pi))/2 is smooth at 0.
    """
    theta = np.linalg.norm(rotvec, axis=1)
    return np.concatenate(
        [np.cos(0.5 * theta)[:, None], 0.5 * np.sinc(theta / (2 * np.pi))[:, None] * rotvec], 1
    )


def _rotation_matrices(quat: np.ndarray) -> np.ndarray:
    """(N, 3, 3) rotation matrices of unit quaternions ``quat`` (N, 4) (w, x, y, z)."""
    w, x, y, z = quat.T
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


class MeshRenderer:
    """Headless RGB frames of rigid bodies (MuJoCo's renderer, EGL) from their own triangle meshes and poses.

    Args:
        meshes: N pairs (vertices (V, 3) [m] in the body frame, faces (F, 3) vertex indices), array-likes or
            tensors; closed, consistently wound (outward) meshes with at least 4 vertices.
        colors: N RGBA tuples in [0, 1], one per mesh; default a ten-colour palette, cycled.
        width: image width [pixels].
        height: image height [pixels].
        camera: free-camera settings ``lookat`` (3,) [m], ``distance`` [m], ``azimuth`` [deg], ``elevation`` [deg]
            (MuJoCo's ``MjvCamera``); keys left out are chosen at the first render so that all meshes, at
            that render's poses, fill the view (about the given ``lookat``, if given) from azimuth 135 deg and
            elevation -30 deg. ``self.camera`` can be moved between renders (checked at each render).
        floor: height z [m] of a checkered ground plane (drawn only; checker cells as large as the largest
            mesh's bounding box side), or None for no ground.

    Raises:
        ValueError: on malformed meshes, colours, camera values, floor or image size.
        RuntimeError: when no OpenGL context can be made (mujoco imported before ``MUJOCO_GL=egl`` was set, or an
            image larger than the framebuffer limit).

    A renderer draws on the thread that made it (its OpenGL context is current there; EGL refuses another thread
    with ``EGL_BAD_ACCESS``): make one per thread.
    """

    def __init__(
        self,
        meshes: Sequence[tuple[npt.ArrayLike | torch.Tensor, npt.ArrayLike | torch.Tensor]],
        colors: Sequence[Sequence[float]] | None = None,
        *,
        width: int = 480,
        height: int = 480,
        camera: Mapping[str, float | Sequence[float]] | None = None,
        floor: float | None = None,
    ) -> None:
        self._renderer = None  # set last, so that close() works on a half-built instance
        if len(meshes) == 0:
            raise ValueError("meshes must hold at least one (vertices, faces) pair")
        for name, value in (("width", width), ("height", height)):
            if not (is_int(value) and value >= 1):
                raise ValueError(f"{name} must be a positive int [pixels], got {value!r}")
        width, height = int(width), int(height)
        if colors is None:
            colors = [_PALETTE[i % len(_PALETTE)] for i in range(len(meshes))]
        rgba0 = _numpy(colors, "colors", np.float64)
        _check_colours(rgba0, len(meshes), "colors")
        if floor is not None and not (is_real(floor) and math.isfinite(floor)):
            raise ValueError(f"floor must be a finite height [m] or None, got {floor!r}")
        camera = dict(camera or {})
        unknown = set(camera) - set(_CAMERA_KEYS)
        if unknown:
            raise ValueError(f"camera keys must be among {_CAMERA_KEYS}, got {sorted(unknown)}")
        _check_camera(camera, "camera")

        spec = mujoco.MjSpec()
        self._vertices = []  # (V, 3) body-frame vertices per mesh, for the automatic framing
        for i, (verts, faces) in enumerate(meshes):
            verts = _numpy(verts, f"meshes[{i}] vertices", np.float64)
            faces = _numpy(faces, f"meshes[{i}] faces", np.int64)
            if verts.ndim != 2 or verts.shape[1] != 3 or len(verts) < 4 or not np.isfinite(verts).all():
                raise ValueError(
                    f"meshes[{i}] vertices must be a finite (V, 3) array, V >= 4; got {verts.shape}"
                )
            if faces.ndim != 2 or faces.shape[1] != 3 or len(faces) == 0:
                raise ValueError(f"meshes[{i}] faces must be a (F, 3) array, F >= 1; got {faces.shape}")
            if faces.min() < 0 or faces.max() >= len(verts):
                raise ValueError(f"meshes[{i}] faces index outside [0, {len(verts)})")
            self._vertices.append(verts)
            mesh = spec.add_mesh()
            mesh.name = f"mesh{i}"
            mesh.uservert = verts.ravel().tolist()
            mesh.userface = faces.ravel().tolist()
            body = spec.worldbody.add_body(name=f"body{i}", mocap=True)
            body.add_geom(
                type=mujoco.mjtGeom.mjGEOM_MESH,
                meshname=mesh.name,
                contype=0,
                conaffinity=0,
                rgba=rgba0[i].tolist(),
            )
        if floor is not None:
            cell = max(float(np.ptp(v, axis=0).max()) for v in self._vertices)
            texture = spec.add_texture(
                name="checker",
                type=mujoco.mjtTexture.mjTEXTURE_2D,
                builtin=mujoco.mjtBuiltin.mjBUILTIN_CHECKER,
                rgb1=[0.82, 0.84, 0.86],
                rgb2=[0.62, 0.65, 0.68],
                width=256,
                height=256,
            )
            material = spec.add_material(name="floor", texuniform=True, texrepeat=[0.5 / cell] * 2)
            material.textures[mujoco.mjtTextureRole.mjTEXROLE_RGB] = texture.name
            spec.worldbody.add_geom(
                type=mujoco.mjtGeom.mjGEOM_PLANE,
                size=[0, 0, 1],  # 0: drawn to the far clipping plane
                pos=[0, 0, float(floor)],
                material="floor",
                contype=0,
                conaffinity=0,
            )
        spec.worldbody.add_light(
            directional=True, dir=[0.3, 0.2, -1.0], diffuse=[0.6] * 3, specular=[0.1] * 3, castshadow=False
        )
        self._model = spec.compile()
        self._model.vis.global_.offwidth = max(width, self._model.vis.global_.offwidth)
        self._model.vis.global_.offheight = max(height, self._model.vis.global_.offheight)
        self._model.vis.headlight.ambient = [0.35] * 3
        self._model.vis.headlight.diffuse = [0.45] * 3
        self._data = mujoco.MjData(self._model)
        self._mocap = self._model.body_mocapid[1 : len(meshes) + 1]  # body i + 1 carries mesh i
        self._geoms = np.array([self._model.body_geomadr[i + 1] for i in range(len(meshes))])  # mesh i's geom
        self._colors = self._model.geom_rgba[self._geoms].copy()
        self._camera_settings = camera
        self._aspect = width / height
        self._framed = False
        self.camera = mujoco.MjvCamera()
        self.camera.type = mujoco.mjtCamera.mjCAMERA_FREE
        if _forked_after_egl_context and _egl_backend():
            raise RuntimeError(
                "this process was forked from one that had made an EGL context (it rendered), and its first EGL "
                "call would hang: start it with the 'spawn' or 'forkserver' start method instead, e.g. "
                "gym.make_vec(..., vectorization_mode='async', vector_kwargs={'context': 'spawn'}) or "
                "multiprocessing.get_context('spawn')"
            )
        try:
            renderer = mujoco.Renderer(self._model, height, width)
        except mujoco.FatalError as e:
            backend = getattr(mujoco.gl_context.GLContext, "__module__", None)
            raise RuntimeError(
                f"MuJoCo could not make a {width} x {height} off-screen renderer ({e}; OpenGL backend {backend}, "
                "chosen when mujoco was first imported): an image larger than the GPU's framebuffer limit fails "
                "so; without an X display, MUJOCO_GL=egl must be set before anything imports mujoco (cfd_torch, "
                "pytorch_kinematics and gymnasium's MuJoCo environments do)"
            ) from e
        renderer.scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = 0
        renderer.scene.flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = 0
        self._renderer = renderer
        global _made_egl_context
        _made_egl_context = _made_egl_context or _egl_backend()
        _OPEN.add(self)
        global _atexit_registered
        if not _atexit_registered:
            atexit.register(_close_open_renderers)
            _atexit_registered = True

    def _frame(self, translation: np.ndarray, rotations: np.ndarray) -> None:
        """Fill the camera settings not given at construction so that the bounding sphere of all meshes, at
        poses (translation (N, 3) [m], rotations (N, 3, 3)), fills the view (its narrower angle: the horizontal one
        in a portrait image)."""
        world = np.concatenate(
            [v @ r.T + t for v, r, t in zip(self._vertices, rotations, translation, strict=True)]
        )
        lo, hi = world.min(0), world.max(0)
        if "lookat" in self._camera_settings:  # the sphere about the given point that holds every mesh
            lookat = np.asarray(self._camera_settings["lookat"], dtype=np.float64)
            radius = float(np.linalg.norm(world - lookat, axis=1).max())
        else:
            lookat = 0.5 * (lo + hi)
            radius = 0.5 * float(np.linalg.norm(hi - lo))
        half = half_view_angle(self._model.vis.global_.fovy, self._aspect)
        settings = {
            "lookat": lookat,
            "distance": _FRAME_MARGIN * max(radius, 1e-9) / np.sin(half),
            "azimuth": _DEFAULT_AZIMUTH,
            "elevation": _DEFAULT_ELEVATION,
        } | self._camera_settings
        self.camera.lookat[:] = np.asarray(settings["lookat"], dtype=np.float64)
        self.camera.distance = float(settings["distance"])
        self.camera.azimuth = float(settings["azimuth"])
        self.camera.elevation = float(settings["elevation"])
        self._framed = True

    def render(
        self, poses: npt.ArrayLike | torch.Tensor, colors: npt.ArrayLike | torch.Tensor | None = None
    ) -> np.ndarray:
        """One RGB frame of the bodies at ``poses``.

        Args:
            poses: (N, 6) array-like or tensor, translation [m] then rotation vector (axis * angle [rad]) per
                body; body-frame vertex X is drawn at R(omega) X + t.
            colors: (N, 4) RGBA in [0, 1] for this frame only, or None for the construction colours.

        Returns:
            A new (height, width, 3) uint8 array.
        """
        if self._renderer is None:
            raise RuntimeError("render() called after close()")
        poses = _numpy(poses, "poses", np.float64)
        n = len(self._vertices)
        if poses.shape != (n, 6) or not np.isfinite(poses).all():
            raise ValueError(f"poses must be a finite ({n}, 6) array, got shape {poses.shape}")
        if colors is None:
            rgba = self._colors
        else:
            rgba = _numpy(colors, "colors", np.float32)
            _check_colours(rgba, n, "colors")
        quat = _quaternions(poses[:, 3:])
        if not self._framed:
            self._frame(poses[:, :3], _rotation_matrices(quat))
        cam = self.camera
        _check_camera(
            {"lookat": np.array(cam.lookat), "distance": float(cam.distance), "azimuth": float(cam.azimuth),
             "elevation": float(cam.elevation)}, "self.camera",
        )  # fmt: skip
        self._model.geom_rgba[self._geoms] = rgba
        # Clipping planes sit at znear and zfar (0.01 and 50 by default) times the model extent.
        self._model.stat.extent = self.camera.distance
        self._data.mocap_pos[self._mocap] = poses[:, :3]
        self._data.mocap_quat[self._mocap] = quat
        mujoco.mj_kinematics(self._model, self._data)
        self._renderer.update_scene(self._data, camera=self.camera)
        return self._renderer.render()

    def close(self) -> None:
        """Free the OpenGL context; idempotent."""
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None

    def __del__(self) -> None:
        # Argument binding may have failed before __init__ ran.
        if getattr(self, "_renderer", None) is not None:
            self.close()


# GIF stores each frame's delay in whole hundredths of a second, and browsers play a delay under 20 ms as 100 ms
_MIN_DELAY_CS = 2
_MAX_DELAY_CS = 65535  # 16 bits


def write_gif(frames: Sequence[np.ndarray], path: str | os.PathLike, fps: float = 30) -> Path:
    """Write frames as a looping animated GIF that plays at ``fps``.

    GIF stores each frame's delay in whole hundredths of a second, and browsers play delays under 20 ms as 100 ms;
    so above 50 frames per second every k-th frame is kept (k = ceil(fps / 50), and the last frame), each shown
    for k / fps: the clip keeps its duration. Delays are rounded to the nearest 10 ms (at 60 fps: every second
    frame, 30 ms each, a clip 10 % short).

    Args:
        frames: T uint8 (H, W, 3) RGB arrays (NumPy) of one shape.
        path: output file, ending in ``.gif``; missing parent folders are created.
        fps: frames per second, a finite number > 0 (at most 655 s per frame).

    Returns:
        The path written. Pillow merges consecutive identical frames into one longer frame.
    """
    if len(frames) == 0:
        raise ValueError("frames must not be empty")
    for i, f in enumerate(frames):
        if not isinstance(f, np.ndarray):
            raise TypeError(f"frames[{i}] must be a NumPy array, got {type(f).__name__}")
    shape = frames[0].shape
    for i, f in enumerate(frames):
        if f.dtype != np.uint8 or f.ndim != 3 or f.shape[2] != 3 or f.shape != shape:
            raise ValueError(
                f"frames[{i}] must be a uint8 (H, W, 3) array of frames[0]'s shape {shape}, got {f.dtype} {f.shape}"
            )
    if not (is_real(fps) and math.isfinite(fps) and fps > 0):
        raise ValueError(f"fps must be a finite number > 0, got {fps!r}")
    path = Path(path)
    if path.suffix.lower() != ".gif":
        raise ValueError(f"path must end in .gif (write_gif writes GIF), got {str(path)!r}")
    every = max(1, math.ceil(fps * _MIN_DELAY_CS / 100.0 - 1e-9))
    delay_cs = round(100.0 * every / fps)
    if delay_cs > _MAX_DELAY_CS:
        raise ValueError(
            f"fps must be at least {100.0 / _MAX_DELAY_CS:.3g} (a GIF frame lasts at most 655 s), got {fps}"
        )
    keep = list(range(0, len(frames), every))
    if keep[-1] != len(frames) - 1:
        keep.append(len(frames) - 1)
    path.parent.mkdir(parents=True, exist_ok=True)
    first, *rest = (Image.fromarray(frames[i]) for i in keep)
    first.save(path, format="GIF", save_all=True, append_images=rest, duration=10 * delay_cs, loop=0)
    return path
