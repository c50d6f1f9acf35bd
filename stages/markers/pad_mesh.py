"""The pad surface of a deform frame as a vertex grid for ray tracing.

The solver grid (grid_x, grid_y; surface_z, the negative sag on TacTip's dome) is resampled
bilinearly over the pad (`upsample` vertices per solver cell and axis; < 1 is coarser), plus
one ring of vertices MARGIN x the pad beyond its edge, so that a sheared pad still fills the
camera's frame; displacement fields (ux, uy, uz mm; uz < 0 into the pad) move the vertices.
Texture coordinates are the undeformed (material) coordinates, u = x / pad_w + 1/2,
v = y / pad_h + 1/2, so whatever is looked up at (u, v) moves with the material.  A pad with
an outline (on_pad not all True: the dome) keeps the grid cells that touch it; its outline is
cut per ray sample where the bilinear on_pad crosses 1/2, smoother than whole grid cells.
"""
from __future__ import annotations

import numpy as np

MARGIN = 0.1                     # the outer vertex ring's distance beyond the pad edge, fraction of the pad


def _axis_weights(src: np.ndarray, dst: np.ndarray):
    """Left neighbour index and weight of each dst coordinate on the sorted src axis (clamped)."""
    pos = np.interp(dst, src, np.arange(src.size, dtype=float))
    i0 = np.clip(np.floor(pos).astype(int), 0, src.size - 2)
    return i0, (pos - i0)


def _resample(field: np.ndarray, wy, wx) -> np.ndarray:
    """Bilinear resampling of an (h, w, ...) field onto a grid given by axis weights."""
    (iy, ty), (ix, tx) = wy, wx
    extra = (1,) * (field.ndim - 2)
    tx, ty = tx.reshape(1, -1, *extra), ty.reshape(-1, 1, *extra)
    rows = field[:, ix] * (1 - tx) + field[:, ix + 1] * tx
    return rows[iy] * (1 - ty) + rows[iy + 1] * ty


class PadMesh:
    """The pad's vertex grid: undeformed positions, texture coordinates, faces, and the
    deformed positions and normals of a displacement field (all (ny, nx, ...) grids)."""

    def __init__(self, grid_x, grid_y, surface_z, on_pad, pad_size_mm, upsample: float = 1.0):
        gx, gy = np.asarray(grid_x, float), np.asarray(grid_y, float)
        surface_z, on_pad = np.asarray(surface_z, float), np.asarray(on_pad, bool)
        if surface_z.shape != (gy.size, gx.size) or on_pad.shape != surface_z.shape:
            raise ValueError(f"surface_z {surface_z.shape} / on_pad {on_pad.shape} do not match "
                             f"the grid ({gy.size}, {gx.size})")
        if not on_pad.any():
            raise ValueError("on_pad is all False: no pad surface to render")
        if not on_pad.all():        # the dome's rim: carry its height outwards, no step to 0
            from scipy.ndimage import distance_transform_edt
            _, (iy, ix) = distance_transform_edt(~on_pad, return_indices=True)
            surface_z = surface_z[iy, ix]
        self.pad = tuple(float(v) for v in pad_size_mm)
        if not upsample > 0:
            raise ValueError(f"render upsample {upsample!r}: must be > 0")
        step = min(np.diff(gx).mean(), np.diff(gy).mean()) / float(upsample)
        self.x, self.y = (np.concatenate([[-(0.5 + MARGIN) * p],
                                          np.linspace(-p / 2, p / 2, int(np.ceil(p / step - 1e-9)) + 1),
                                          [(0.5 + MARGIN) * p]]) for p in self.pad)
        self.wx, self.wy = _axis_weights(gx, self.x), _axis_weights(gy, self.y)
        xx, yy = np.meshgrid(self.x, self.y)
        self.base = np.stack([xx, yy, _resample(surface_z, self.wy, self.wx)], -1)
        self.uv = np.stack([xx / self.pad[0] + 0.5, yy / self.pad[1] + 0.5], -1)
        self.on_pad = _resample(on_pad.astype(float), self.wy, self.wx).astype(np.float32)
        self.bounded = not on_pad.all()
        self.faces = self._faces(self.on_pad > 0)
        self.fill_z = float(self.base[..., 2][self.on_pad >= 0.5].min())   # nearest pad point: the rim

    @staticmethod
    def _faces(inside: np.ndarray) -> np.ndarray:
        """Two triangles per grid cell touching the pad, wound so their normals face the
        camera (-z)."""
        ny, nx = inside.shape
        idx = np.arange(ny * nx).reshape(ny, nx)
        a, b, c, d = idx[:-1, :-1], idx[:-1, 1:], idx[1:, :-1], idx[1:, 1:]
        tris = np.concatenate([np.stack([a, c, b], -1).reshape(-1, 3),
                               np.stack([b, c, d], -1).reshape(-1, 3)])
        return tris[inside.ravel()[tris].any(1)].astype(np.uint32)

    @property
    def shape(self):
        return self.base.shape[:2]

    def positions(self, displacement: np.ndarray) -> np.ndarray:
        """Deformed vertex positions (ny, nx, 3) mm for a solver-grid displacement (h, w, 3)."""
        return self.base + _resample(np.asarray(displacement, float), self.wy, self.wx)

    @staticmethod
    def normals(positions: np.ndarray) -> np.ndarray:
        """Unit vertex normals (ny, nx, 3) of a deformed grid, facing the camera (-z)."""
        dy, dx = np.gradient(positions, axis=(0, 1))
        n = np.cross(dy, dx)
        return n / np.linalg.norm(n, axis=-1, keepdims=True)

    def grid_index(self, x: np.ndarray, y: np.ndarray):
        """Fractional (col, row) on the vertex grid of material coordinates x, y (mm)."""
        return (np.interp(x, self.x, np.arange(self.x.size, dtype=float)),
                np.interp(y, self.y, np.arange(self.y.size, dtype=float)))
