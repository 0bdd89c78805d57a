"""`lidar-slam merge`: several runs (sessions recorded at different times, each in its own frame)
into one saved map.

session (a run folder opened as a session: its map, its pose graph, its per-frame poses) ->
loops (Scan Context over every other session's keyframes, every column shift, verified by the
loop-closure ICP gates) -> solve (each session's anchor from the consensus of its verified
loops, a weak prior on it, the reference's fixed; one GNC solve of every session's odometry,
intra- and inter-session loops; then a guided pass where the solve puts sessions together) ->
changes (what one session saw where another saw through: appeared / disappeared) -> build (the
merged map folder, per-session poses and summaries; `run --extend`). See docs/merge.md.
"""
