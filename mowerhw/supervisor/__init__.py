"""The permit supervisor (docs/design.md §8): a small process that alone writes the permit
frames (ISB, heartbeat, status). Estimation runs in a child process and renews a *permit
lease* with every decision; the supervisor permits only while it holds a fresh lease and its
own checks hold, so a stalled, slow or crashed estimator halts the deck and can never delay
the supervisor's frames.

Modules: :mod:`.lease` (the lease and the supervisor's decision: pure), :mod:`.link` (the
estimation side's end of the pipe), :mod:`.process` (the supervisor process), :mod:`.child`
(the estimation process's entry point).
"""
