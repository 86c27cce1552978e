"""Z-depth and instance-mask rendering of a settled scene.

Two interchangeable backends produce the same images (pixel centres at the declared
OpenCV intrinsics, depth = z along the optical axis, id 0 = ground or nothing, id k =
rock k, depth 0 where no geometry is hit):

* ``"gl"``: MuJoCo's offscreen OpenGL renderer (depth buffer + segmentation pass).
  Needs a headless GL: ``MUJOCO_GL=egl`` with Mesa's EGL + llvmpipe (Debian:
  ``libegl1 libegl-mesa0 libgl1-mesa-dri libopengl0``) or ``MUJOCO_GL=osmesa``
  (``libosmesa6``).  ``physics.headless_gl_platform`` picks whichever is installed.
* ``"raster"``: a vectorised numpy z-buffer rasteriser, no system packages needed.
  Measured on a busy 2-core machine, 4 views at 1920x1080: EGL 1.2–2.1 s, raster
  1.7–3.1 s, OSMesa 2.7–3.4 s.  The two backends agree to ~1e-4 units in depth and
  >99.99 % of mask pixels (tested).

``"auto"`` uses GL when it can render here and the raster backend otherwise.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

from .cameras import Camera
from .physics import import_mujoco

Backend = Literal["auto", "gl", "raster"]


@dataclass
class RenderedView:
    """One rendered camera: z-depth (0 = nothing hit) and ids (0 = ground/none, k = rock k)."""

    depth: np.ndarray  # (H, W) float32
    ids: np.ndarray  # (H, W) int32


# --------------------------------------------------------------------------- raster
def rasterize(
    camera: Camera,
    vertices: np.ndarray,
    faces: np.ndarray,
    face_ids: np.ndarray,
    *,
    near: float = 1.0,
    chunk: int = 2_000_000,
) -> RenderedView:
    """Z-buffer rasterisation of a triangle soup into depth + id images.

    Pixel (row v, column u) samples the image point (u, v) exactly (OpenCV: pixel
    centres at integer coordinates).  1/z is affine in screen space, so each triangle
    gets a plane ``1/z = a u + b v + c`` and depth is exact (perspective-correct).
    Back faces are culled (rocks are closed meshes, the ground is seen from above);
    triangles reaching behind ``near`` are dropped, which is safe because the rig never
    looks at geometry that close.

    Scanline expansion, vectorised: every (triangle, pixel row) pair gets the exact
    column span where the row crosses the triangle, then spans are expanded into
    pixels with ``np.repeat``, so only covered pixels are ever visited.  Pixels are
    processed in chunks of about ``chunk`` to bound memory.
    """
    h, w = camera.height, camera.width
    uv, z = camera.project(vertices)
    tri_z = z[faces]
    tri_uv = uv[faces]
    # Signed area in pixel space: the image's y axis points down, so front faces
    # (counter-clockwise seen from outside) have a negative cross product here.
    e1 = tri_uv[:, 1] - tri_uv[:, 0]
    e2 = tri_uv[:, 2] - tri_uv[:, 0]
    area = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
    keep = (tri_z > near).all(axis=1) & (area < -1e-9)
    y_lo = np.ceil(tri_uv[:, :, 1].min(axis=1))
    y_hi = np.floor(tri_uv[:, :, 1].max(axis=1))
    x_lo = tri_uv[:, :, 0].min(axis=1)
    x_hi = tri_uv[:, :, 0].max(axis=1)
    keep &= (y_hi >= np.maximum(y_lo, 0)) & (y_lo <= h - 1) & (x_hi >= 0) & (x_lo <= w - 1)
    keep &= np.floor(x_hi) >= np.ceil(x_lo)
    idx = np.nonzero(keep)[0]
    tri_uv, tri_iz, area, ids = tri_uv[idx], 1.0 / tri_z[idx], area[idx], face_ids[idx]
    y0 = np.clip(y_lo[idx], 0, h - 1).astype(np.int64)
    y1 = np.clip(y_hi[idx], 0, h - 1).astype(np.int64)

    # Plane of 1/z over the screen: Cramer's rule on the three corners.
    (ua, va), (ub, vb), (uc, vc) = tri_uv[:, 0].T, tri_uv[:, 1].T, tri_uv[:, 2].T
    za, zb, zc = tri_iz.T
    pa = ((zb - za) * (vc - va) - (zc - za) * (vb - va)) / area
    pb = ((zc - za) * (ub - ua) - (zb - za) * (uc - ua)) / area
    pc = za - pa * ua - pb * va

    # Rows: one (triangle, row) pair per scanline crossing a triangle.
    n_rows = y1 - y0 + 1
    rt = np.repeat(np.arange(len(idx)), n_rows)
    ry = (np.arange(n_rows.sum()) - np.repeat(np.cumsum(n_rows) - n_rows, n_rows) + y0[rt]).astype(np.float64)
    # Column span: where the row meets the three edges (edges that straddle the row).
    xs_min = np.full(len(rt), np.inf)
    xs_max = np.full(len(rt), -np.inf)
    for i, j in ((0, 1), (1, 2), (2, 0)):
        ui, vi = tri_uv[rt, i, 0], tri_uv[rt, i, 1]
        uj, vj = tri_uv[rt, j, 0], tri_uv[rt, j, 1]
        straddle = (np.minimum(vi, vj) <= ry) & (np.maximum(vi, vj) >= ry) & (vi != vj)
        with np.errstate(divide="ignore", invalid="ignore"):
            x = ui + (ry - vi) * (uj - ui) / (vj - vi)
        xs_min = np.where(straddle, np.minimum(xs_min, x), xs_min)
        xs_max = np.where(straddle, np.maximum(xs_max, x), xs_max)
    # A hair of tolerance so that pixels exactly on a shared edge are not lost to rounding.
    c0 = np.clip(np.ceil(xs_min - 1e-9), 0, w - 1).astype(np.int64)
    c1 = np.clip(np.floor(xs_max + 1e-9), 0, w - 1).astype(np.int64)
    valid = (xs_max + 1e-9 >= 0) & (xs_min - 1e-9 <= w - 1) & (np.floor(xs_max + 1e-9) >= np.ceil(xs_min - 1e-9))
    rt, ry, c0, c1 = rt[valid], ry[valid].astype(np.int64), c0[valid], c1[valid]
    n_px = c1 - c0 + 1

    izbuf = np.zeros(h * w)  # 1/z: larger is nearer; 0 = nothing hit
    idbuf = np.zeros(h * w, dtype=np.int32)
    bounds = np.searchsorted(np.cumsum(n_px), np.arange(chunk, n_px.sum() + chunk, chunk), side="left") + 1
    start = 0
    for end in np.unique(np.minimum(np.append(bounds, len(n_px)), len(n_px))):
        if end <= start:
            continue
        n = n_px[start:end]
        t = np.repeat(rt[start:end], n)
        py = np.repeat(ry[start:end], n)
        px = np.arange(n.sum()) - np.repeat(np.cumsum(n) - n, n) + np.repeat(c0[start:end], n)
        start = end
        inv_z = pa[t] * px + pb[t] * py + pc[t]
        pix = py * w + px
        np.maximum.at(izbuf, pix, inv_z)
        win = inv_z >= izbuf[pix]
        idbuf[pix[win]] = ids[t[win]]
    hit = izbuf > 0
    with np.errstate(divide="ignore"):
        depth = np.where(hit, 1.0 / izbuf, 0.0)
    return RenderedView(depth=depth.astype(np.float32).reshape(h, w), ids=np.where(hit, idbuf, 0).astype(np.int32).reshape(h, w))


def scene_triangles(
    rock_vertices: list[np.ndarray], rock_faces: list[np.ndarray], terrain_vertices: np.ndarray, terrain_faces: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One triangle soup of the world: rocks get id 1..N, the ground id 0."""
    verts = [terrain_vertices]
    faces = [terrain_faces]
    ids = [np.zeros(len(terrain_faces), dtype=np.int32)]
    offset = len(terrain_vertices)
    for k, (v, f) in enumerate(zip(rock_vertices, rock_faces), start=1):
        verts.append(v)
        faces.append(f + offset)
        ids.append(np.full(len(f), k, dtype=np.int32))
        offset += len(v)
    return np.concatenate(verts), np.concatenate(faces), np.concatenate(ids)


# --------------------------------------------------------------------------- MuJoCo GL
def gl_available() -> bool:
    """Whether MuJoCo can render offscreen here (checked once per process by rendering
    a one-geom model: a context alone can be created by a backend that cannot render,
    e.g. GLFW without a display)."""
    global _GL_OK
    if _GL_OK is None:
        try:
            mujoco = import_mujoco()
            model = mujoco.MjModel.from_xml_string("<mujoco><worldbody><geom size='1'/></worldbody></mujoco>")
            data = mujoco.MjData(model)
            mujoco.mj_forward(model, data)
            with mujoco.Renderer(model, 8, 8) as r:
                r.update_scene(data)
                r.render()
            _GL_OK = True
        except Exception:  # any missing library / driver / display shows up as some exception
            _GL_OK = False
    return _GL_OK


_GL_OK: bool | None = None


def add_gl_cameras(spec: Any, cameras: list[Camera]) -> None:
    """Add the rig to a MuJoCo spec as fixed cameras with the exact pinhole intrinsics.

    MuJoCo cameras look along -z with y up (OpenGL), so the OpenCV rotation is turned by
    diag(1, -1, -1).  The frustum is given by sensor size = image size in pixels, focal
    length in pixels and the principal point offset; the half-pixel shift moves
    OpenGL's pixel-centre sampling (at +0.5) onto OpenCV's integer pixel coordinates.
    """
    mujoco = import_mujoco()
    w = max(c.width for c in cameras)
    h = max(c.height for c in cameras)
    spec.visual.global_.offwidth = max(spec.visual.global_.offwidth, w)
    spec.visual.global_.offheight = max(spec.visual.global_.offheight, h)
    spec.visual.quality.offsamples = 0  # no multisampling: ids and depth must not blend
    for c in cameras:
        r_gl = c.pose[:3, :3] @ np.diag([1.0, -1.0, -1.0])
        quat = np.zeros(4)
        mujoco.mju_mat2Quat(quat, r_gl.ravel())
        spec.worldbody.add_camera(
            name=c.name,
            pos=c.pose[:3, 3].tolist(),
            quat=quat.tolist(),
            resolution=[c.width, c.height],
            sensor_size=[float(c.width), float(c.height)],
            focal_pixel=[c.fx, c.fy],
            principal_pixel=[c.cx - c.width / 2.0 - 0.5, c.cy - c.height / 2.0 - 0.5],
        )


def render_gl(model: Any, data: Any, cameras: list[Camera], rock_geoms: np.ndarray) -> list[RenderedView]:
    """Render depth + ids with MuJoCo's offscreen renderer (cameras added by add_gl_cameras)."""
    mujoco = import_mujoco()

    geom_to_rock = np.zeros(model.ngeom + 1, dtype=np.int32)  # index -1 (background) -> 0
    geom_to_rock[rock_geoms] = np.arange(1, len(rock_geoms) + 1)
    out = []
    # Near/far planes relative to the model extent: keep the near plane well in front of
    # the closest geometry and the far plane beyond the farthest ground.
    model.vis.map.znear = 1.0 / model.stat.extent
    model.vis.map.zfar = 20000.0 / model.stat.extent
    by_size: dict[tuple[int, int], Any] = {}
    try:
        for c in cameras:
            key = (c.height, c.width)
            if key not in by_size:
                by_size[key] = mujoco.Renderer(model, height=c.height, width=c.width)
            r = by_size[key]
            r.disable_segmentation_rendering()
            r.enable_depth_rendering()
            r.update_scene(data, camera=c.name)
            depth = r.render().copy()
            r.disable_depth_rendering()
            r.enable_segmentation_rendering()
            r.update_scene(data, camera=c.name)
            seg = r.render()
            geom = np.where(seg[..., 1] == int(mujoco.mjtObj.mjOBJ_GEOM), seg[..., 0], -1)
            hit = geom >= 0
            ids = geom_to_rock[geom]
            out.append(RenderedView(depth=np.where(hit, depth, 0.0).astype(np.float32), ids=ids.astype(np.int32)))
    finally:
        for r in by_size.values():
            r.close()
    return out
