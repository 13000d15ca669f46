"""Recordings: the MCAP recorder and reader (:mod:`.mcap`) and the replay through the runtime
core (:mod:`.replay`)."""
