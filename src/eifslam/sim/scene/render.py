"""Render the built-in scene with the exact pinhole model, and write it as a data set folder.

Each :class:`~eifslam.sim.scene.layout.Surface` is a textured plane. For a texture texel
``(i, j)`` centred at ``(s, t) = ((i + 0.5) du, (j + 0.5) dv)`` on the plane, the pixel is
given exactly by the plane-induced homography ``H = K [du u_c, dv v_c, X0_c]`` (camera-
frame axes and texel-centre origin), so :func:`cv2.warpPerspective` (which samples the
texture through ``H^-1`` at every pixel centre) draws the face exactly as the ground truth
sees it. Occlusion is resolved per pixel with an inverse-depth buffer: on a plane
``n_c . X_c = d_c`` the inverse depth of pixel ``(u, v)`` is ``n_c . K^-1 [u, v, 1] / d_c``,
linear in the pixel. Pixels whose ray meets the plane behind the camera get a negative
inverse depth and are discarded, so faces crossing the camera plane need no clipping
beyond a bounding box. Textures are mip-mapped (area-averaged halving) and the level is picked
per face from the texture-to-image scale at the centre of its visible part, which keeps far faces from aliasing.

Image conventions as in :mod:`eifslam.geometry.camera`: pixel centres at integer coordinates.
"""

from __future__ import annotations

import functools
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import cv2
import numpy as np
import yaml
from numpy.typing import NDArray

from ...errors import ConfigError, DatasetError
from ...geometry.rotations import quat_wxyz_to_xyzw
from .layout import BuiltinScene, Surface
from .photos import photo_texture
from .textures import ellipse_alpha, make_texture

__all__ = ["render_frame", "render_scene", "BACKGROUND_BGR"]

#: colour of pixels no surface covers (none should remain in the built-in trajectory)
BACKGROUND_BGR = (128, 128, 128)
_NEAR = 0.01  # metres


@dataclass(frozen=True)
class _Texture:
    """Mip-map pyramid of a face's BGRA texture and the texel sizes (metres) of every level.

    Every level covers the whole face: level ``L`` has ``n_L`` texels along ``u`` of size
    ``size_u / n_L``, texel ``i`` centred at ``(i + 0.5) * du[L]``.
    """

    levels: tuple[NDArray[np.uint8], ...]
    du: tuple[float, ...]
    dv: tuple[float, ...]


@functools.lru_cache(maxsize=512)
def _cached_levels(nu: int, nv: int, seed: int, shade: tuple[float, float, float], shape: str,
                   material: str = "procedural") -> tuple[NDArray[np.uint8], ...]:
    """Mip-map pyramid of a BGRA texture; cached, so re-made scenes reuse their textures.

    Each level halves the previous one with area averaging (sizes rounded), so it still
    spans the whole face. ``material`` is ``"procedural"`` (:func:`make_texture`) or a
    photograph material of :func:`~eifslam.sim.scene.photos.photo_texture`.
    """
    if material == "procedural":
        bgr = make_texture(nu, nv, seed, shade)
    else:
        bgr = photo_texture(material, nu, nv, seed, shade)
    alpha = ellipse_alpha(nu, nv) if shape == "ellipse" else np.full((nv, nu), 255, np.uint8)
    levels = [np.dstack([bgr, alpha])]
    while min(levels[-1].shape[:2]) >= 16:
        h, w = levels[-1].shape[:2]
        levels.append(cv2.resize(levels[-1], (max(1, round(w / 2)), max(1, round(h / 2))),
                                 interpolation=cv2.INTER_AREA))
    for lev in levels:
        lev.flags.writeable = False
    return tuple(levels)


def _build_texture(face: Surface) -> _Texture:
    """The texture of one face (texel counts rounded from ``size / texel``)."""
    nu = max(2, int(round(face.size_u / face.texel)))
    nv = max(2, int(round(face.size_v / face.texel)))
    levels = _cached_levels(nu, nv, face.seed, tuple(face.shade), face.shape, face.material)
    du = tuple(face.size_u / lev.shape[1] for lev in levels)
    dv = tuple(face.size_v / lev.shape[0] for lev in levels)
    return _Texture(levels, du, dv)


def _textures(scene: BuiltinScene) -> list[_Texture]:
    """The scene's textures, in the order of ``scene.surfaces``."""
    return [_build_texture(f) for f in scene.surfaces]


def _clip_near(poly_c: NDArray[np.float64], near: float) -> NDArray[np.float64]:
    """Clip a convex polygon (camera frame, ``(M, 3)``) to ``z >= near``."""
    out = []
    m = len(poly_c)
    for i in range(m):
        a, b = poly_c[i], poly_c[(i + 1) % m]
        ina, inb = a[2] >= near, b[2] >= near
        if ina:
            out.append(a)
        if ina != inb:
            t = (near - a[2]) / (b[2] - a[2])
            out.append(a + t * (b - a))
    return np.array(out).reshape(-1, 3)


def _mip_level(H: NDArray[np.float64], uv: NDArray[np.float64], n_levels: int) -> int:
    """Pyramid level for a homography ``H`` (texel -> pixel) evaluated at pixel ``uv``.

    Uses the geometric mean of the texel-per-pixel scale (square root of the Jacobian
    determinant of ``H^-1``), rounded in log2.
    """
    Hi = np.linalg.inv(H)
    x = Hi @ np.array([uv[0], uv[1], 1.0])
    J = (Hi[:2, :2] - np.outer(x[:2] / x[2], Hi[2, :2])) / x[2]
    scale = np.sqrt(abs(np.linalg.det(J)))
    if not np.isfinite(scale) or scale <= 1.0:
        return 0
    return int(min(n_levels - 1, max(0, np.round(np.log2(scale)))))


def _draw_face(img: NDArray[np.uint8], ibuf: NDArray[np.float32], face: Surface, tex: _Texture,
               K: NDArray[np.float64], R_cw: NDArray[np.float64], p: NDArray[np.float64]) -> None:
    """Draw one face into ``img`` where it is nearer than ``ibuf`` (inverse depth), in place."""
    n_w = face.normal
    if n_w @ (p - face.origin) <= 1e-9:  # back face
        return
    poly = _clip_near((face.corners - p) @ R_cw.T, _NEAR)
    if len(poly) < 3:
        return
    proj = poly[:, :2] / poly[:, 2:3] * [K[0, 0], K[1, 1]] + K[:2, 2]
    h, w = ibuf.shape
    x0 = int(np.clip(np.floor(proj[:, 0].min()), 0, w))
    x1 = int(np.clip(np.ceil(proj[:, 0].max()) + 1, 0, w))
    y0 = int(np.clip(np.floor(proj[:, 1].min()), 0, h))
    y1 = int(np.clip(np.ceil(proj[:, 1].max()) + 1, 0, h))
    if x1 <= x0 or y1 <= y0:
        return
    u_c, v_c = R_cw @ face.axis_u, R_cw @ face.axis_v
    O_c = R_cw @ (face.origin - p)
    H0 = K @ np.column_stack([tex.du[0] * u_c, tex.dv[0] * v_c, O_c])
    centre = np.clip(proj.mean(0), [x0, y0], [x1 - 1, y1 - 1])
    level = _mip_level(H0, centre, len(tex.levels))
    du, dv = tex.du[level], tex.dv[level]
    # texel (i, j) of this level is centred at (s, t) = ((i + 0.5) du, (j + 0.5) dv)
    H = K @ np.column_stack([du * u_c, dv * v_c, O_c + 0.5 * du * u_c + 0.5 * dv * v_c])
    T = np.array([[1.0, 0.0, -x0], [0.0, 1.0, -y0], [0.0, 0.0, 1.0]])
    warped = cv2.warpPerspective(tex.levels[level], T @ H, (x1 - x0, y1 - y0),
                                 flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                                 borderValue=(0, 0, 0, 0))
    n_c = R_cw @ n_w
    d_c = float(n_c @ (R_cw @ (face.origin - p)))
    m = np.linalg.solve(K.T, n_c) / d_c  # inverse depth = m . [u, v, 1]
    us = np.arange(x0, x1, dtype=np.float32)
    vs = np.arange(y0, y1, dtype=np.float32)
    inv = (np.float32(m[0]) * us[None, :] + np.float32(m[1]) * vs[:, None] + np.float32(m[2]))
    sub = ibuf[y0:y1, x0:x1]
    mask = (warped[:, :, 3] >= 64) & (inv > sub) & (inv > 0)
    np.copyto(img[y0:y1, x0:x1], warped[:, :, :3], where=mask[:, :, None])
    np.copyto(sub, inv, where=mask)


def render_frame(scene: BuiltinScene, k: int, noise_sigma: float = 0.0, blur_sigma: float = 0.0,
                 rng: np.random.Generator | None = None) -> NDArray[np.uint8]:
    """Render frame ``k`` of the scene.

    Parameters
    ----------
    scene : BuiltinScene
    k : int
        Frame index, ``0 <= k < scene.n_frames``.
    noise_sigma : float
        Standard deviation of additive Gaussian pixel noise, in grey levels (0-255).
    blur_sigma : float
        Standard deviation of a Gaussian blur in pixels, applied before the noise.
    rng : numpy.random.Generator, optional
        Source of the noise; default ``default_rng((scene.seed, k))``, so a frame is
        reproducible.

    Returns
    -------
    (height, width, 3) uint8 BGR image.
    """
    if not 0 <= int(k) < scene.n_frames:
        raise ConfigError(f"frame index {k} out of range [0, {scene.n_frames})")
    if not (np.isfinite(noise_sigma) and noise_sigma >= 0 and np.isfinite(blur_sigma) and blur_sigma >= 0):
        raise ConfigError(f"noise and blur sigmas must be >= 0, got {noise_sigma}, {blur_sigma}")
    cam = scene.camera
    K = cam.K
    R_cw = scene.rotation_wc(k).T
    p = scene.positions[k]
    img = np.empty((cam.height, cam.width, 3), np.uint8)
    img[:] = BACKGROUND_BGR
    ibuf = np.zeros((cam.height, cam.width), np.float32)
    for face, tex in zip(scene.surfaces, _textures(scene)):
        _draw_face(img, ibuf, face, tex, K, R_cw, p)
    if blur_sigma > 0:
        img = cv2.GaussianBlur(img, (0, 0), float(blur_sigma))
    if noise_sigma > 0:
        rng = rng if rng is not None else np.random.default_rng((scene.seed, int(k)))
        noise = rng.standard_normal(img.shape, dtype=np.float32) * np.float32(noise_sigma)
        noisy = img.astype(np.float32) + noise
        img = np.clip(np.rint(noisy), 0, 255).astype(np.uint8)
    return img


def boxes_json(scene: BuiltinScene) -> dict:
    """The ``boxes.json`` content: box corners (world, metres) and the ratio box."""
    return {
        "frame": "world: origin at the table-top centre, z up, metres",
        "corner_order": "bottom 4 then top 4, counter-clockwise from above, from local (-w/2,-l/2)",
        "ratio_box_index": scene.ratio_box_index,
        "ratio_box_name": scene.boxes[scene.ratio_box_index].name,
        "top_face_ratio": round(scene.box_ratio_true, 12),
        "boxes": [
            {"name": b.name, "size_wlh": [float(x) for x in b.size], "yaw_rad": float(b.yaw),
             "center": b.center.tolist(), "corners": b.corners.tolist()}
            for b in scene.boxes
        ],
    }


def _write_metadata(scene: BuiltinScene, out: Path) -> None:
    """camera.yaml, times.txt, groundtruth.tum, boxes.json (scenes with boxes), README.md."""
    cam = scene.camera
    camera = {"model": "pinhole", "width": cam.width, "height": cam.height, "fx": float(cam.fx),
              "fy": float(cam.fy), "cx": float(cam.cx), "cy": float(cam.cy),
              "distortion": [0.0, 0.0, 0.0, 0.0, 0.0]}
    (out / "camera.yaml").write_text(yaml.safe_dump(camera, sort_keys=False, default_flow_style=None))
    (out / "times.txt").write_text("".join(f"{t:.6f}\n" for t in scene.timestamps))
    q = quat_wxyz_to_xyzw(scene.quats_wxyz)
    lines = [f"# timestamp tx ty tz qx qy qz qw (camera-to-world; world: {scene.world_frame})\n"]
    for t, pk, qk in zip(scene.timestamps, scene.positions, q):
        lines.append(f"{t:.6f} " + " ".join(f"{v:.9f}" for v in (*pk, *qk)) + "\n")
    (out / "groundtruth.tum").write_text("".join(lines))
    if scene.boxes:
        (out / "boxes.json").write_text(json.dumps(boxes_json(scene), indent=1))
    (out / "README.md").write_text(f"# eifslam built-in scene\n\n{scene.description}\n")


def render_scene(scene: BuiltinScene, out_dir: str | Path, noise_sigma: float = 0.0,
                 blur_sigma: float = 0.0, seed: int | None = None,
                 progress: Callable[[int], None] | None = None) -> Path:
    """Render every frame and write the data set folder layout.

    Writes ``out_dir/images/000000.png ...``, ``camera.yaml``, ``times.txt``,
    ``groundtruth.tum`` (``timestamp tx ty tz qx qy qz qw``, camera-to-world),
    ``boxes.json`` (when the scene has boxes) and ``README.md``.

    Parameters
    ----------
    scene : BuiltinScene
    out_dir : str or Path
        Created if missing; existing files of the same names are overwritten.
    noise_sigma, blur_sigma : float
        As in :func:`render_frame`.
    seed : int, optional
        Seed of the pixel noise (default: the scene's seed).
    progress : callable, optional
        Called with the frame index after each image is written (e.g. a progress bar).

    Returns
    -------
    Path of the folder.
    """
    out = Path(out_dir)
    try:
        (out / "images").mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise DatasetError(f"cannot create output folder {out}: {exc}") from exc
    _write_metadata(scene, out)
    rng = np.random.default_rng(scene.seed if seed is None else seed)
    for k in range(scene.n_frames):
        img = render_frame(scene, k, noise_sigma, blur_sigma, rng)
        path = out / "images" / f"{k:06d}.png"
        if not cv2.imwrite(str(path), img):
            raise DatasetError(f"cannot write image {path}")
        if progress is not None:
            progress(k)
    return out
