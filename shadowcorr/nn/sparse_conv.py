"""Submanifold sparse 3D convolution on ragged batches of voxels.

A sparse voxel set is given as ``coords`` (N, 3) int64 integer grid coordinates and
``batch`` (N,) int64 scene ids; voxels of different scenes never interact even when
their coordinates coincide.  A *submanifold* convolution produces outputs only at the
input sites (the active set does not dilate), so a stack of them keeps the voxel set
fixed, which is what a per-voxel embedding network needs.

For a kernel of size ``s = 2r + 1`` the ``s**3`` kernel offsets are ordered
lexicographically over ``(dx, dy, dz)`` with each component in ``range(-r, r + 1)``
(``dx`` slowest), so the centre tap is index 13 of 27 and 62 of 125.  Kernels are
stored as ``(kernel offset, in, out)``, the layout of the reference checkpoint.

Neighbour lookup is a vectorised hash join (:class:`VoxelHash`): every (scene, x, y, z)
is packed into one int64 key, and the query ``coords + offset`` is the site's key plus
a per-offset constant, found with one gather in a dense key table (or ``searchsorted``
in the sorted keys when the key space is too large for a table).  There is no Python
loop over voxels; the only loop is over the 27 / 125 kernel offsets when accumulating
``features[neighbour] @ kernel[offset]``.
"""

from __future__ import annotations

import itertools
import math

import torch
from torch import nn

from ._take import take

__all__ = ["kernel_offsets", "VoxelHash", "neighbour_index", "SubmanifoldConv3d", "PointwiseConv3d"]

# Keys must stay below 2**63 (one bit of head-room).
_MAX_KEY_SPACE = 2**62


def kernel_offsets(kernel_size: int, device: torch.device | str | None = None) -> torch.Tensor:
    """All integer offsets of a cubic kernel, ``(kernel_size**3, 3)`` int64.

    Ordered lexicographically over ``(dx, dy, dz)``, each in ``range(-r, r + 1)`` with
    ``r = kernel_size // 2``; row ``kernel_size**3 // 2`` is the centre ``(0, 0, 0)``.
    """
    if kernel_size < 1 or kernel_size % 2 == 0:
        raise ValueError(f"kernel_size must be a positive odd integer, got {kernel_size}")
    r = kernel_size // 2
    rng = range(-r, r + 1)
    return torch.tensor(list(itertools.product(rng, rng, rng)), dtype=torch.int64, device=device)


class VoxelHash:
    """Vectorised lookup table from (scene, x, y, z) to row index.

    Each scene gets its own key box: its voxels' bounding box grown by ``reach`` on
    every side, laid out one after the other in one int64 key space
    (``key = base[scene] + ((x - lo_x) * sy + (y - lo_y)) * sz + (z - lo_z)``).
    Because of the margin, a site's key plus the per-scene key delta of an offset with
    all ``|component| <= reach`` is exactly the key of ``site + offset`` (no wrap into a
    neighbouring row of the box), which makes :meth:`offset_lookup` a few elementwise
    ops and one lookup per query.

    Lookups use a dense key -> row array when the key space is small (the usual case:
    a scene of a few thousand voxels spans well under a million cells; one gather per
    query), else the sorted keys and ``searchsorted``.  Empty stretches of a scene are
    squeezed out of its box first: per axis, a gap between consecutive occupied values
    wider than ``2 * reach + 2`` is narrowed to that.  An offset of at most ``reach``
    from a site never crosses such a gap, so ``site + offset`` keeps its meaning, and a
    field of clusters far apart (a site survey, tiles a kilometre apart) still gets a
    dense table.

    Args:
        coords: (N, 3) int64 integer coordinates.
        batch: (N,) int64 scene ids.
        reach: key-box margin, the largest offset component :meth:`offset_lookup`
            will be asked for.

    Raises:
        ValueError: on bad shapes, duplicate (scene, coordinate) sites (a sparse tensor
        has one feature vector per site, so duplicates make lookups ambiguous), or a
        coordinate range too large to pack into int64 keys.
    """

    #: Dense tables up to max(this, 64 * N) cells (int32: 64 MiB at this floor); 0 = never.  A
    #: 482-rock field of 15 m synthetic tiles needs 9.6M and 16M cells for the grid k-NN's wider
    #: balls: the network took 2.9 s there with this floor against 3.9 s with 8M (one thread).
    dense_cells: int = 1 << 24

    def __init__(self, coords: torch.Tensor, batch: torch.Tensor, reach: int = 0) -> None:
        if coords.ndim != 2 or coords.shape[1] != 3:
            raise ValueError(f"coords must be (N, 3), got {tuple(coords.shape)}")
        if batch.shape != (coords.shape[0],):
            raise ValueError(f"batch must be ({coords.shape[0]},), got {tuple(batch.shape)}")
        if coords.dtype.is_floating_point or batch.dtype.is_floating_point:
            raise ValueError("coords and batch must be integer tensors")
        if reach < 0:
            raise ValueError(f"reach must be >= 0, got {reach}")
        self.n = n = coords.shape[0]
        self.reach = reach
        device = coords.device
        coords = coords.to(torch.int64)
        batch = batch.to(torch.int64)
        self.scenes, self.scene_of_row = torch.unique(batch, return_inverse=True)
        n_scenes = self.scenes.numel()
        self._axis_min = [int(coords[:, a].min()) if n else 0 for a in range(3)]
        self._axis_span = [int(coords[:, a].max()) - self._axis_min[a] + 1 if n else 1 for a in range(3)]
        squeezed_axes = [self._squeeze_axis(self.scene_of_row, coords[:, a] - self._axis_min[a], self._axis_span[a],
                                            2 * reach + 2) for a in range(3)]
        # Per axis, the occupied (scene, value) keys and their squeezed values, for lookup().
        self._axes = [(occupied, squeezed) for occupied, squeezed, _ in squeezed_axes]
        given = coords
        coords = torch.stack([rows for _, _, rows in squeezed_axes], dim=1)
        idx3 = self.scene_of_row.unsqueeze(1).expand(-1, 3)
        lo = torch.full((n_scenes, 3), torch.iinfo(torch.int64).max, dtype=torch.int64, device=device)
        hi = torch.full((n_scenes, 3), torch.iinfo(torch.int64).min, dtype=torch.int64, device=device)
        self.lo = lo.scatter_reduce(0, idx3, coords, "amin") - reach
        self.hi = hi.scatter_reduce(0, idx3, coords, "amax") + reach
        size = self.hi - self.lo + 1  # (S, 3)
        # Per-axis strides of each scene's box; check overflow in Python integers.
        sizes = size.tolist()
        volumes = [sx * sy * sz for sx, sy, sz in sizes]
        total = sum(volumes)
        if total >= _MAX_KEY_SPACE:
            raise ValueError(
                f"coordinate range too large for int64 voxel keys ({total} cells); "
                "pass grid indices, not positions in scene units"
            )
        self.stride = torch.stack([size[:, 1] * size[:, 2], size[:, 2], torch.ones_like(size[:, 2])], dim=1)
        self.base = torch.tensor([0, *volumes[:-1]], dtype=torch.int64, device=device).cumsum(0)
        self.keys = self._encode(self.scene_of_row, coords)  # per row, in row order

        self.dense: torch.Tensor | None = None
        if self.dense_cells and total <= max(self.dense_cells, 64 * n):
            self.dense = torch.full((total,), -1, dtype=torch.int32, device=device)
            rows = torch.arange(n, dtype=torch.int32, device=device)
            self.dense[self.keys] = rows
            if n and not bool((self.dense[self.keys] == rows).all()):
                self._raise_duplicate(given, batch, self.keys, torch.sort(self.keys))
        else:
            self.sorted_keys, self.perm = torch.sort(self.keys)
            self._raise_duplicate(given, batch, self.keys, (self.sorted_keys, self.perm))

    @staticmethod
    def _squeeze_axis(scene: torch.Tensor, values: torch.Tensor, span: int, widest: int
                      ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """One axis (``values`` in ``[0, span)``): the sorted occupied (scene, value) keys, their
        squeezed values, and each row's squeezed value.  Gaps wider than ``widest`` within a
        scene are narrowed to it."""
        key = scene * span + values
        occupied, row_slot = torch.unique(key, return_inverse=True)
        occ_scene = occupied // span
        occ_value = occupied % span
        step = torch.diff(occ_value, prepend=occ_value[:1])
        step = torch.where(torch.diff(occ_scene, prepend=occ_scene[:1]) != 0, 0, step.clamp(max=widest))
        squeezed = occ_value[:1] + torch.cumsum(step, dim=0) if occupied.numel() else occ_value
        return occupied, squeezed, squeezed[row_slot]

    def _squeeze_query(self, scene: torch.Tensor, coords: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Squeezed coordinates of arbitrary queries and whether each lies on occupied values
        of its scene on every axis (else no site can be there)."""
        out, found = [], torch.ones(coords.shape[:-1], dtype=torch.bool, device=coords.device)
        for a, (occupied, squeezed) in enumerate(self._axes):
            values = coords[..., a]
            lo_value = int(self._axis_min[a])
            span = self._axis_span[a]
            inside = (values >= lo_value) & (values < lo_value + span)
            key = scene * span + (values - lo_value).clamp(0, span - 1)
            pos = torch.searchsorted(occupied, key).clamp_(max=max(occupied.numel() - 1, 0))
            found &= inside & (occupied[pos] == key)
            out.append(squeezed[pos])
        return torch.stack(out, dim=-1), found

    @staticmethod
    def _raise_duplicate(coords: torch.Tensor, batch: torch.Tensor, keys: torch.Tensor, sorted_perm) -> None:
        sorted_keys, perm = sorted_perm
        dup = sorted_keys[1:] == sorted_keys[:-1]
        if bool(dup.any()):
            row = int(perm[1:][dup][0])
            raise ValueError(
                f"duplicate voxel site: row {row} (scene {int(batch[row])}, coords {coords[row].tolist()}) "
                "occurs more than once"
            )

    def _encode(self, scene: torch.Tensor, coords: torch.Tensor) -> torch.Tensor:
        return self.base[scene] + ((coords - self.lo[scene]) * self.stride[scene]).sum(dim=-1)

    def _find(self, keys: torch.Tensor, dtype: torch.dtype = torch.int64) -> torch.Tensor:
        if self.n == 0:
            return torch.full_like(keys, -1, dtype=dtype)
        if self.dense is not None:
            return take(self.dense, keys).to(dtype)
        pos = torch.searchsorted(self.sorted_keys, keys).clamp_(max=self.n - 1)
        return torch.where(take(self.sorted_keys, pos) == keys, take(self.perm, pos), -1).to(dtype)

    def lookup(self, coords: torch.Tensor, batch: torch.Tensor) -> torch.Tensor:
        """Row of the site at ``(batch, coords)`` or -1, for arbitrary queries.

        Args:
            coords: (..., 3) int64.
            batch: (...) int64, broadcastable against ``coords[..., 0]``.
        """
        shape = torch.broadcast_shapes(coords.shape[:-1], batch.shape)
        if self.n == 0:
            return torch.full(shape, -1, dtype=torch.int64, device=coords.device)
        coords = coords.expand(*shape, 3)
        batch = batch.expand(shape)
        scene = torch.searchsorted(self.scenes, batch).clamp_(max=self.scenes.numel() - 1)
        # On squeezed coordinates: a query off the occupied values of an axis holds no site.
        coords, occupied = self._squeeze_query(scene, coords.to(torch.int64))
        lo, hi = self.lo[scene], self.hi[scene]
        inside = occupied & (self.scenes[scene] == batch) & ((coords >= lo) & (coords <= hi)).all(dim=-1)
        # Clamp so out-of-box queries still encode to in-range keys; ``inside`` drops them.
        keys = self._encode(scene, torch.minimum(torch.maximum(coords, lo), hi))
        return torch.where(inside, self._find(keys), -1)

    def offset_lookup(self, offsets: torch.Tensor, rows: slice | torch.Tensor | None = None, *,
                      site_major: bool = False, dtype: torch.dtype = torch.int64) -> torch.Tensor:
        """Rows of the sites at ``coords[r] + offsets[o]`` (same scene), or -1.

        Args:
            offsets: (K, 3) int64 with every component in ``[-reach, reach]``.
            rows: which sites to query (default: all).
            site_major: return (R, K) instead of (K, R).
            dtype: ``torch.int64``, or ``torch.int32`` (half the memory traffic for consumers
                that stay in 32 bits, such as the grid k-NN's sort keys).

        Returns:
            (K, R) offset-major, or (R, K) with ``site_major``.
        """
        if offsets.numel() and int(offsets.abs().max()) > self.reach:
            raise ValueError(f"offsets reach {int(offsets.abs().max())} > the table's reach {self.reach}")
        if dtype not in (torch.int64, torch.int32):
            raise ValueError(f"dtype must be torch.int64 or torch.int32, got {dtype}")
        offsets = offsets.to(device=self.keys.device, dtype=torch.int64)
        sel = slice(None) if rows is None else rows
        base = self.keys[sel]  # (R,)
        if self.scenes.numel() == 1:
            stride = self.stride[:1]  # one scene: one key delta per offset
        else:
            stride = self.stride[self.scene_of_row[sel]]  # (R, 3)
        # Written out instead of ``offsets @ stride.T``: integer matmul has no CUDA kernel.
        if site_major:  # built (R, K) rather than transposed, so the gather reads contiguous keys
            delta = stride[:, 0:1] * offsets[:, 0] + stride[:, 1:2] * offsets[:, 1] + stride[:, 2:3] * offsets[:, 2]
            return self._find(base.unsqueeze(1) + delta, dtype)
        delta = offsets[:, 0:1] * stride[:, 0] + offsets[:, 1:2] * stride[:, 1] + offsets[:, 2:3] * stride[:, 2]
        return self._find(delta + base, dtype)  # (K, R)


def neighbour_index(coords: torch.Tensor, batch: torch.Tensor, offsets: torch.Tensor) -> torch.Tensor:
    """Index of the voxel at ``coords + offset`` in the same scene, for every offset.

    Args:
        coords: (N, 3) int64 integer voxel coordinates, unique within a scene.
        batch: (N,) int64 scene id of each voxel.
        offsets: (K, 3) int64 offsets (e.g. :func:`kernel_offsets`).

    Returns:
        (K, N) int64: ``out[o, i]`` is the row of the voxel at ``coords[i] + offsets[o]``
        with ``batch == batch[i]``, or ``-1`` when there is none.

    Raises:
        ValueError: see :class:`VoxelHash` (bad shapes, duplicate sites, huge ranges).
    """
    if offsets.ndim != 2 or offsets.shape[1] != 3:
        raise ValueError(f"offsets must be (K, 3), got {tuple(offsets.shape)}")
    reach = int(offsets.abs().max()) if offsets.numel() else 0
    return VoxelHash(coords, batch, reach=reach).offset_lookup(offsets)


class SubmanifoldConv3d(nn.Module):
    """Submanifold sparse 3D convolution (outputs only at the input sites).

    ``out[i] = sum_o features[nb(i, o)] @ kernel[o] (+ bias)`` over the kernel offsets
    ``o`` whose neighbour ``nb(i, o)`` (the voxel at ``coords[i] + offset[o]`` in the
    same scene) exists.

    Args:
        in_channels, out_channels: feature widths.
        kernel_size: odd cube side (3 -> 27 taps, 5 -> 125 taps).
        bias: add a learned bias (the reference convolutions have none).

    Parameters:
        kernel: (kernel_size**3, in_channels, out_channels), checkpoint layout.
        bias: (out_channels,) or ``None``.
    """

    def __init__(self, in_channels: int, out_channels: int, kernel_size: int, bias: bool = False) -> None:
        super().__init__()
        self.in_channels = in_channels
        self.out_channels = out_channels
        self.kernel_size = kernel_size
        self.register_buffer("offsets", kernel_offsets(kernel_size), persistent=False)
        self.centre = kernel_size**3 // 2
        self.kernel = nn.Parameter(torch.empty(kernel_size**3, in_channels, out_channels))
        self.bias = nn.Parameter(torch.empty(out_channels)) if bias else None
        self.reset_parameters()

    def reset_parameters(self) -> None:
        # Same scale as a dense Conv3d's default init: fan-in counts every tap.
        bound = 1.0 / math.sqrt(self.in_channels * self.kernel_size**3)
        nn.init.uniform_(self.kernel, -bound, bound)
        if self.bias is not None:
            nn.init.uniform_(self.bias, -bound, bound)

    def extra_repr(self) -> str:
        return (
            f"{self.in_channels}, {self.out_channels}, kernel_size={self.kernel_size}, "
            f"bias={self.bias is not None}"
        )

    def forward(
        self,
        features: torch.Tensor,
        coords: torch.Tensor,
        batch: torch.Tensor,
        neighbours: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """Apply the convolution.

        Args:
            features: (N, in_channels) float.
            coords: (N, 3) int64 integer coordinates (unique per scene).
            batch: (N,) int64 scene ids.
            neighbours: optional precomputed ``neighbour_index(coords, batch, offsets)``
                (K, N) table, to share one lookup between layers of equal kernel size.

        Returns:
            (N, out_channels) features at the input sites.
        """
        if features.ndim != 2 or features.shape[1] != self.in_channels:
            raise ValueError(f"features must be (N, {self.in_channels}), got {tuple(features.shape)}")
        if neighbours is None:
            neighbours = neighbour_index(coords, batch, self.offsets)
        if neighbours.shape != (self.kernel.shape[0], features.shape[0]):
            raise ValueError(
                f"neighbours must be ({self.kernel.shape[0]}, {features.shape[0]}), got {tuple(neighbours.shape)}"
            )
        # The centre offset always finds the voxel itself (sites are unique), so it is
        # one dense matmul without any gather.
        out = features @ self.kernel[self.centre]
        for o in range(self.kernel.shape[0]):
            if o == self.centre:
                continue
            nb = neighbours[o]
            rows = (nb >= 0).nonzero().squeeze(1)
            if rows.numel() == 0:  # common on shells: most offsets hit nothing
                continue
            # In place: an out-of-place index_add would copy all of ``out`` per offset.
            # Autograd is fine with it, since no backward needs ``out`` itself.
            out.index_add_(0, rows, features[nb[rows]] @ self.kernel[o])
        return out + self.bias if self.bias is not None else out


class PointwiseConv3d(nn.Module):
    """1x1x1 sparse convolution, i.e. a per-voxel affine map.

    Stored like the reference's last layer: ``kernel`` (in, out) and ``bias`` (out,),
    so ``out = features @ kernel + bias``.  It needs no coordinates.
    """

    def __init__(self, in_channels: int, out_channels: int, bias: bool = True) -> None:
        super().__init__()
        self.in_channels = in_channels
        self.out_channels = out_channels
        self.kernel = nn.Parameter(torch.empty(in_channels, out_channels))
        self.bias = nn.Parameter(torch.empty(out_channels)) if bias else None
        bound = 1.0 / math.sqrt(in_channels)
        nn.init.uniform_(self.kernel, -bound, bound)
        if self.bias is not None:
            nn.init.uniform_(self.bias, -bound, bound)

    def extra_repr(self) -> str:
        return f"{self.in_channels}, {self.out_channels}, bias={self.bias is not None}"

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        """(N, in) -> (N, out)."""
        out = features @ self.kernel
        return out + self.bias if self.bias is not None else out
