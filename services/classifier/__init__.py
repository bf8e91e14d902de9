"""classifier: clusters each LiDAR scan and labels clusters background / flying / unknown
(seed 000, sec. III-B). First version; later issues add the BFS flood-fill rule B and rule A
with d_close against tentative-occupied voxels."""
