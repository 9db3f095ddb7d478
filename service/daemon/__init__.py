"""The netpose daemon: frame source -> pipeline -> autopilot link and telemetry.

    loop.py     the frame loop (`Daemon.iterate`) and its start, stop and reload
    stats.py    counters of the loop, read without being reset
    status.py   the 1 Hz status (systemd line, telemetry status, queryable state), summaries
    outputs.py  per-frame hand-over to the link and to telemetry
    events.py   rate-limited log lines about state changes
    ports.py    the protocols the loop uses of its drivers
    wiring.py   the one module that constructs drivers and wires them to the loop
"""
