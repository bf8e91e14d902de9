"""The compiled voxel algorithms of seed 000 on hand-made cases: the cube search of rule A, the flood
fill of rule B (Alg. 1), Euclidean clustering (eq. 13–15). The ray traversal: test_voxels_traversal.py."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.sparse.csgraph import connected_components
from scipy.spatial.distance import cdist

from schemas.voxels import STATE_FREE, STATE_TENTATIVE, STATE_UNKNOWN
from services.lib.voxels.kernels import clusters_near_occupied, enclosed_by_free, euclidean_clusters

SHAPE = np.array([20, 16, 12])
CORNER = np.array([-1.0, -2.0, 0.5])
VOXEL = 0.5


def grid_states(fill=STATE_UNKNOWN):
    return np.full(int(SHAPE.prod()), fill, np.uint8)


def flat(*ijk):
    return np.ravel_multi_index(tuple(np.array(ijk).T), tuple(SHAPE))


def test_rule_a_finds_a_tentative_voxel_within_d_close_only():
    states = grid_states()
    states[flat((10, 8, 6))] = STATE_TENTATIVE
    centre = CORNER + (np.array([10, 8, 6]) + 0.5) * VOXEL
    points = np.array([centre + [1.4, 0, 0], centre + [1.6, 0, 0], centre + [0, 0, 3.0]])
    near = clusters_near_occupied(points, np.array([0, 1, 2]), 3, np.ones(3, bool), states, CORNER, VOXEL, SHAPE, 1.5)
    assert near.tolist() == [True, False, False]
    states[flat((10, 8, 6))] = STATE_UNKNOWN  # uncertain voxels are not background
    near = clusters_near_occupied(points, np.array([0, 1, 2]), 3, np.ones(3, bool), states, CORNER, VOXEL, SHAPE, 1.5)
    assert not near.any()


def flood(states, seeds, low, high):
    visited = np.zeros(len(states), np.uint8)
    queue = np.empty(len(states), np.int64)
    result = enclosed_by_free(states, SHAPE, np.asarray(seeds, np.int64).reshape(-1), np.asarray(low), np.asarray(high),
                              visited, queue)
    assert not visited.any(), "the scratch is left as it was found"
    return result


def shell(states, centre, radius, state):
    """Surround `centre` by a cubic shell of `state` at Chebyshev distance `radius`."""
    for ijk in np.ndindex(*SHAPE):
        if max(abs(np.array(ijk) - centre)) == radius:
            states[flat(ijk)] = state


def test_flood_fill_rule_b_enclosed_open_and_bounded_by_the_search_cube():
    centre = np.array([10, 8, 6])
    states = grid_states()
    shell(states, centre, 2, STATE_FREE)  # a 5×5×5 room of free space around unknown voxels
    seed = [flat(centre)]
    assert flood(states, seed, centre - 4, centre + 5)  # walled off by free space: a flying object
    states[flat(centre + [2, 0, 0])] = STATE_UNKNOWN  # a gap in the wall ...
    assert not flood(states, seed, centre - 4, centre + 5)  # ... leads to the cube's border: unknown
    states[flat(centre + [3, 0, 0])] = STATE_FREE  # the gap is a dead end inside the cube
    shell_outer = grid_states(STATE_UNKNOWN)
    shell(shell_outer, centre, 3, STATE_FREE)
    states[shell_outer == STATE_FREE] = STATE_FREE
    assert flood(states, seed, centre - 4, centre + 5)
    states[flat(centre + [1, 1, 0])] = STATE_TENTATIVE  # something occupied reachable inside: background-bound
    assert not flood(states, seed, centre - 4, centre + 5)


def test_flood_fill_stops_at_the_cube_not_at_the_walls_beyond_it():
    centre = np.array([10, 8, 6])
    states = grid_states()
    shell(states, centre, 4, STATE_FREE)  # walls 4 voxels away
    assert flood(states, [flat(centre)], centre - 5, centre + 6)  # the cube reaches past the walls
    assert not flood(states, [flat(centre)], centre - 3, centre + 4)  # a cube inside the walls is left


def test_euclidean_clusters_equal_the_connected_components_of_the_distance_graph():
    rng = np.random.default_rng(3)
    points = np.vstack([rng.normal(c, 0.6, (40, 3)) for c in ([0, 0, 0], [5, 0, 0], [0, 6, 1], [2.2, 0, 0])])
    labels, count = euclidean_clusters(points, 1.5)
    reference_count, reference = connected_components(cdist(points, points) <= 1.5, directed=False)
    assert count == reference_count
    pairs = {(a, b) for a, b in zip(labels, reference)}
    assert len(pairs) == count  # the same partition, whatever the numbering
    assert labels[0] == 0 and list(dict.fromkeys(labels)) == list(range(count))  # first-appearance order
    assert euclidean_clusters(np.zeros((0, 3)), 1.5)[1] == 0


@pytest.mark.parametrize("seed, count", [(1, 300), (2, 1500), (3, 4000)])
def test_euclidean_clusters_on_sparse_and_dense_random_clouds(seed, count):
    """Cells partly connected inside (sparse) and wholly (dense): the shortcuts must not change the partition."""
    rng = np.random.default_rng(seed)
    points = rng.uniform((0, 0, 0), (30, 30, 6), (count, 3))
    labels, n = euclidean_clusters(points, 1.5)
    reference_count, reference = connected_components(cdist(points, points) <= 1.5, directed=False)
    assert n == reference_count and len(set(zip(labels, reference))) == n


def test_rule_a_ignores_points_far_off_the_map():
    """Found by tests/test_fuzz_messages.py: a return 1e21 m away overflowed int() into reads out of
    bounds (a segfault of the classifier)."""
    states = grid_states(STATE_TENTATIVE)
    points = np.array([[-1.0e21, 2.0e24, 1.0], [1.0e30, 0.0, 0.0], [np.nan, 0.0, 0.0], CORNER + 0.1])
    near = clusters_near_occupied(points, np.arange(4), 4, np.ones(4, bool), states, CORNER, VOXEL, SHAPE, 1.5)
    assert near.tolist() == [False, False, False, True]
