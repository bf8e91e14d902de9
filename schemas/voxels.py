"""What the numbers in LabelSet and VoxelMap mean (seed 000, sec. III-A and III-B).

Label codes of LabelSet.point_labels / voxel_labels, and the G(v) thresholds that split the
occupancy map into the states of eq. 7 (defaults of seed 000's public implementation,
../shared/design.md §6). Every service and viewer reads them from here.
"""
from __future__ import annotations

import numpy as np

# Label codes (uint8 on the wire).
BACKGROUND = 0
FLYING = 1
UNKNOWN = 2
LABEL_NAMES = {BACKGROUND: "background", FLYING: "flying object", UNKNOWN: "unknown"}

# G(v) thresholds of eq. 7: confident occupied >= CONFIDENT_OCCUPIED > tentative occupied
# >= TENTATIVE_OCCUPIED > uncertain (unknown) >= UNCERTAIN > confident free.
CONFIDENT_OCCUPIED = -0.1
TENTATIVE_OCCUPIED = -300.0
UNCERTAIN = -750.0

# Map states, as the viewer colours them (uint8).
STATE_FREE, STATE_UNKNOWN, STATE_TENTATIVE, STATE_OCCUPIED = 0, 1, 2, 3


def map_states(values: np.ndarray) -> np.ndarray:
    """The eq. 7 state of each G value (uint8, STATE_*)."""
    g = np.asarray(values, dtype=np.float32)
    states = np.full(g.shape, STATE_FREE, dtype=np.uint8)
    states[g >= np.float32(UNCERTAIN)] = STATE_UNKNOWN
    states[g >= np.float32(TENTATIVE_OCCUPIED)] = STATE_TENTATIVE
    states[g >= np.float32(CONFIDENT_OCCUPIED)] = STATE_OCCUPIED
    return states
