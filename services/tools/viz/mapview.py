"""A viewer's copy of one UAV's occupancy map, drawn as append-only layers.

What is drawn: display cells of `cell` × `cell` × `cell` voxels (`cell` > 1 decimates), each in
the most telling state of its voxels — occupied (at least tentatively: what rule A takes for
background) or unknown — by the thresholds of eq. 7 (schemas/voxels.py). Only voxels a VoxelMap
ever named count: a never-touched voxel holds the initial "unknown" value and says nothing.
Tentative and confident occupancy are one class here on purpose: at OS0-128 the ground's voxels
near the sensor swing between the two every few scans (grazing rays), and each swing would redraw
the layer holding the voxel; drawn apart they made a recording five times larger.

How: every `drain` puts the cells whose state changed since the last one into a new layer, and
gives back that layer plus every older layer that lost a cell (drawn again without it). A map that
grows by a few hundred cells a second then costs a few hundred cells a second, whatever its size,
and every layer is exact at every mission time. When more than `max_layers` hold cells, all of
them fold into one layer (one full redraw). Layer numbers of emptied layers are used again, so a
mission of any length draws into at most `max_layers` + 1 entities per kind. Pure numpy.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from schemas import voxels
from services.lib.voxels.replica import MapReplica

# What a voxel or cell shows, in increasing importance: a cell shows its most important voxel.
NOTHING, UNKNOWN, OCCUPIED = 0, 1, 2
_SHOWN = np.zeros(256, dtype=np.uint8)  # eq. 7 state -> what is shown (free shows nothing)
_SHOWN[voxels.STATE_UNKNOWN] = UNKNOWN
_SHOWN[voxels.STATE_TENTATIVE] = OCCUPIED
_SHOWN[voxels.STATE_OCCUPIED] = OCCUPIED


@dataclass(frozen=True)
class MapUpdate:
    accepted: bool  # False: a delta of another geometry than ours (wait for a snapshot)
    void: list[int]  # layers drawn before the geometry changed: to be cleared


@dataclass(frozen=True)
class Layer:
    layer: int
    occupied: np.ndarray  # (N, 3) cell centres at least tentatively occupied
    unknown: np.ndarray  # (M, 3) cell centres whose voxels the mapper named and now calls uncertain


class MapView:
    def __init__(self, cell: int, max_layers: int) -> None:
        self.cell = cell
        self.max_layers = max_layers
        self.replica: MapReplica | None = None
        self._voxel_shown: np.ndarray | None = None  # uint8 per voxel
        self._cell_shown: np.ndarray | None = None  # uint8 per display cell
        self._cell_layer: np.ndarray | None = None  # int32 per display cell, -1 in none
        self._cells_shape = (0, 0, 0)
        self._changed: list[np.ndarray] = []  # flat voxel indices whose shown state changed
        self._layers: dict[int, int] = {}  # layer -> cells in it

    @property
    def layers(self) -> int:
        return len(self._layers)

    def apply(self, snapshot: bool, origin, shape, voxel_size: float, default_value: float,
              indices: np.ndarray, values: np.ndarray) -> MapUpdate:
        """Apply one VoxelMap."""
        indices = np.asarray(indices, dtype=np.int64).reshape(-1)
        void: list[int] = []
        replica = self.replica
        if replica is None or (snapshot and not replica.same_geometry(origin, shape, voxel_size)):
            void = sorted(self._layers)
            replica = self.replica = MapReplica(origin, shape, voxel_size, default_value)
            self._reset_cells(replica.shape)
        # A snapshot may also return voxels to the default value: look at those it no longer lists.
        old = replica.grid.reshape(-1)
        before = np.flatnonzero(old != np.float32(replica.default_value)) if snapshot else indices[:0]
        if not replica.apply(snapshot, origin, shape, voxel_size, default_value, indices, values):
            return MapUpdate(accepted=False, void=void)
        flat = replica.grid.reshape(-1)  # a snapshot with another default value makes a new grid
        candidates = np.concatenate([before, indices])  # repeats are harmless: same value twice
        candidates = candidates[(candidates >= 0) & (candidates < flat.size)]
        shown = _SHOWN[voxels.map_states(flat[candidates])]
        moved = shown != self._voxel_shown[candidates]
        self._voxel_shown[candidates[moved]] = shown[moved]
        self._changed.append(candidates[moved])
        return MapUpdate(accepted=True, void=void)

    def _reset_cells(self, shape: tuple[int, int, int]) -> None:
        c = self.cell
        self._voxel_shown = np.zeros(int(np.prod(shape)), dtype=np.uint8)
        self._cells_shape = tuple(-(-s // c) for s in shape)
        cells = int(np.prod(self._cells_shape))
        self._cell_shown = np.zeros(cells, dtype=np.uint8)
        self._cell_layer = np.full(cells, -1, dtype=np.int32)
        self._changed.clear()
        self._layers.clear()

    def drain(self) -> list[Layer]:
        """The new layer and every older one that changed since the last call (empty ones clear)."""
        if self.replica is None or not self._changed:
            return []
        changed_voxels = np.unique(np.concatenate(self._changed))
        self._changed.clear()
        cells = np.unique(self._cell_of(changed_voxels))
        state = self._cell_states(cells)
        moved = state != self._cell_shown[cells]
        cells, state = cells[moved], state[moved]
        if not len(cells):
            return []
        self._cell_shown[cells] = state
        touched = set(self._cell_layer[cells][self._cell_layer[cells] >= 0].tolist())
        for layer in touched:
            self._layers[layer] -= int(np.count_nonzero(self._cell_layer[cells] == layer))
        self._cell_layer[cells] = -1
        drawn = cells[state != NOTHING]
        live = sum(1 for n in self._layers.values() if n)
        new = self._free_layer()
        self._cell_layer[drawn] = new
        if live + (len(drawn) > 0) > self.max_layers:
            return self._fold(new)
        if len(drawn):
            self._layers[new] = len(drawn)
        out = [self._layer(layer) for layer in sorted(touched | ({new} if len(drawn) else set()))]
        self._layers = {layer: n for layer, n in self._layers.items() if n}
        return out

    def _free_layer(self) -> int:
        """The lowest layer number holding no cell (an emptied layer's number is used again)."""
        return next(i for i in range(len(self._layers) + 1) if not self._layers.get(i))

    def _fold(self, layer: int) -> list[Layer]:
        """Every drawn cell into `layer`; all the other layers cleared."""
        old = sorted(set(self._layers) - {layer})
        drawn = self._cell_layer >= 0
        self._cell_layer[drawn] = layer
        self._layers = {layer: int(np.count_nonzero(drawn))}
        return [self._layer(x) for x in old] + [self._layer(layer)]

    def _cell_of(self, flat_voxels: np.ndarray) -> np.ndarray:
        ix, iy, iz = np.unravel_index(flat_voxels, self.replica.shape)
        c = self.cell
        return np.ravel_multi_index((ix // c, iy // c, iz // c), self._cells_shape)

    def _cell_states(self, cells: np.ndarray) -> np.ndarray:
        """Most important shown state among each cell's voxels."""
        c, shape = self.cell, self.replica.shape
        cx, cy, cz = np.unravel_index(cells, self._cells_shape)
        offsets = np.stack(np.meshgrid(*[np.arange(c)] * 3, indexing="ij"), axis=-1).reshape(-1, 3)
        vx = cx[:, None] * c + offsets[None, :, 0]
        vy = cy[:, None] * c + offsets[None, :, 1]
        vz = cz[:, None] * c + offsets[None, :, 2]
        inside = (vx < shape[0]) & (vy < shape[1]) & (vz < shape[2])
        flat = np.ravel_multi_index((np.minimum(vx, shape[0] - 1), np.minimum(vy, shape[1] - 1),
                                     np.minimum(vz, shape[2] - 1)), shape)
        return np.where(inside, self._voxel_shown[flat], NOTHING).max(axis=1).astype(np.uint8)

    def _layer(self, layer: int) -> Layer:
        members = np.flatnonzero(self._cell_layer == layer)
        state = self._cell_shown[members]
        return Layer(layer=layer, occupied=self._centres(members[state == OCCUPIED]),
                     unknown=self._centres(members[state == UNKNOWN]))

    def _centres(self, cells: np.ndarray) -> np.ndarray:
        r, c = self.replica, self.cell
        index = np.stack(np.unravel_index(cells, self._cells_shape), axis=1).reshape(-1, 3)
        return r.origin + (index + 0.5) * c * r.voxel_size

    def cell_size(self) -> float:
        return self.cell * self.replica.voxel_size if self.replica is not None else 0.0
