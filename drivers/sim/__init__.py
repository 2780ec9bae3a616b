"""Simulated devices sharing one deterministic simulated world (patient, robot, cameras, tracker).

Time is the injected clock: on a :class:`hil.clock.ManualClock` a whole procedure runs faster
than real time and reproduces exactly from ``[simulation] seed``.
"""
