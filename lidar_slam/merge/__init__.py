"""`lidar-slam merge`: several runs (sessions recorded at different times, each in its own frame)
into one saved map.

session (a run folder opened as a session: its map, its pose graph, its per-frame poses) ->
loops (one place index over all sessions' keyframes: the nearest Scan Context ring keys of
other sessions, every column shift, verified by the loop-closure ICP gates, a bounded number
per keyframe) -> solve (each session's anchor from the consensus of its verified loops, a weak
prior on it, the reference's fixed; one GNC solve of every session's odometry, intra- and
inter-session loops; then a guided pass where the solve puts sessions together) -> changes
(what one session saw where the nearest keyframes of others saw through: appeared /
disappeared) -> build (the merged map folder, per-session poses and summaries; `run
--extend`). See docs/merge.md.
"""
