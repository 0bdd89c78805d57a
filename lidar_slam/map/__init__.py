"""The map a run leaves: the keyframe store (keyframes), the global point cloud (writer), a
saved run opened as a map (saved), its export as points (export) and as an occupancy grid
(occupancy)."""
