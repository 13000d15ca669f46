"""The status page (issue 19): a plan view of the map with the live pose, the containment
decision, the sensors and, while teaching, the boundary and landmarks as they grow.

It runs in a process of its own (:mod:`.server`, started by the permit supervisor when
``web.enabled``, or by hand with ``mowerhw web``), reads the daemon only through its control
socket (:mod:`.feed`: the read-only ``live`` command, 5–10 times a second while a browser
is connected) and forwards the operator's commands there once the token checks out
(:mod:`.commands`, :mod:`.token`). So a slow, absent or hostile browser can cost the daemon
at most the control socket's own paced requests; it never touches the permit.
"""
