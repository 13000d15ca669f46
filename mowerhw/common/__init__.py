"""Types and conventions every layer shares (docs/design.md §3): rotations and quaternions
(:mod:`.geometry`), timestamped samples (:mod:`.samples`), the time-ordered sample buffer
(:mod:`.buffer`), host/device clock mapping (:mod:`.clocksync`), atomic file writes
(:mod:`.fileio`), hand-written YAML (:mod:`.yamlfile`) and the progress bar
(:mod:`.progress`). Imports nothing else of mowerhw."""
