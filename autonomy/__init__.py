"""Pure algorithms of the companion: numpy in, numpy out.

Nothing in this package does I/O, reads a clock, opens a socket or touches asyncio, and
nothing here imports :mod:`drivers` or :mod:`companion` (a test checks this).
"""
